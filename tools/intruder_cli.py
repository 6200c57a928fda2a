"""`covey intruder`: fly one simulated vehicle that does not cooperate through the fleet.

It flies a straight line at a constant speed, from `--from-ne-m` to `--to-ne-m` at `--alt-m`
above the fleet origin, and reports itself on the mesh as traffic (a `TrafficReport` of source
SIM, as a ground station would report a tracked intruder) at `--rate-hz`. It never avoids
anyone: the agents' filters must keep clear of it with full responsibility (agent/traffic.py).
In keyed mode it signs as the station whose key file it is given; agents accept only roster
stations' (and vehicles') signed reports. With `--manned`, it is a manned aircraft: the fleet
keeps the larger separation from it.
"""

from __future__ import annotations

import argparse
import math
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from cli.options import (
    add_mesh_args,
    die,
    finite,
    floats,
    key_file_path,
    mesh_config,
    nobody_answered,
    stop_on_signals,
)
from comms.mesh import Mesh
from comms.schema import MAX_TRAFFIC_TRACK_ID, MAX_VEHICLE_ID, Role, TrafficSource
from comms.session import MeshConfig, MeshUnreachable
from comms.traffic import TrafficTrack, publish_report
from trust.auth import load_auth

DEFAULT_TRACK_ID = 0x0200_0001
"""Outside the 24-bit ICAO space and covey's own block (comms/adsb.py): never a real aircraft."""


@dataclass(frozen=True)
class IntruderConfig:
    """One straight-line intruder."""

    mesh: MeshConfig
    from_ne_m: tuple[float, float]
    """Start (north, east) in metres from the fleet origin."""
    to_ne_m: tuple[float, float]
    """End (north, east) in metres from the fleet origin."""
    speed_m_s: float = 2.0
    """Ground speed along the line."""
    alt_m: float = 10.0
    """Height above the fleet origin."""
    manned: bool = False
    """A manned aircraft (the fleet keeps the larger separation)."""
    rate_hz: float = 5.0
    """Reports per second (ADS-B gives about 1-2; a station's radar more)."""
    gcs_id: int = 1
    """The reporting station's id (keyed mode: the key file's)."""
    track_id: int = DEFAULT_TRACK_ID
    key_file: str | None = None
    """A station key file: the reports are signed (keyed fleets accept only signed reports)."""
    start_delay_s: float = 0.0
    """Hold at the start, reporting, this long before flying."""

    def __post_init__(self) -> None:
        for name in ("speed_m_s", "rate_hz"):
            value = getattr(self, name)
            if not (math.isfinite(value) and 0 < value <= 1000):
                raise ValueError(f"{name}={value} must be within (0, 1000]")
        if not (math.isfinite(self.alt_m) and -100 <= self.alt_m <= 10_000):
            raise ValueError(f"alt_m={self.alt_m} must be within [-100, 10000] m")
        if not (math.isfinite(self.start_delay_s) and 0 <= self.start_delay_s <= 3600):
            raise ValueError(f"start_delay_s={self.start_delay_s} must be within [0, 3600] s")
        if not 1 <= self.gcs_id <= MAX_VEHICLE_ID:
            raise ValueError(f"gcs_id={self.gcs_id} must be within 1..{MAX_VEHICLE_ID}")
        if not 0 <= self.track_id <= MAX_TRAFFIC_TRACK_ID:
            raise ValueError(f"track_id={self.track_id} must fit 32 bits")
        if self.from_ne_m == self.to_ne_m:
            raise ValueError("--from-ne-m and --to-ne-m are the same point: nowhere to fly")

    @property
    def length_m(self) -> float:
        return math.dist(self.from_ne_m, self.to_ne_m)

    @property
    def duration_s(self) -> float:
        return self.start_delay_s + self.length_m / self.speed_m_s


def track_at(cfg: IntruderConfig, t_s: float, stamp_s: float = 0.0) -> TrafficTrack:
    """Where the intruder is `t_s` after it started: p = a + (b - a) min(1, s / |b - a|),
    s = speed (t - delay); its velocity is zero before it leaves and after it arrives."""
    (an, ae), (bn, be) = cfg.from_ne_m, cfg.to_ne_m
    length = cfg.length_m
    flown = min(length, max(0.0, cfg.speed_m_s * (t_s - cfg.start_delay_s)))
    u = flown / length
    moving = 0.0 < cfg.speed_m_s * (t_s - cfg.start_delay_s) < length
    vn, ve = ((bn - an) / length * cfg.speed_m_s, (be - ae) / length * cfg.speed_m_s)
    return TrafficTrack(
        cfg.track_id,
        (an + (bn - an) * u, ae + (be - ae) * u, -cfg.alt_m),
        (vn, ve, 0.0) if moving else (0.0, 0.0, 0.0),
        TrafficSource.SIM,
        cfg.manned,
        stamp_s,
        1 if cfg.manned else 14,  # ADS-B emitter: light aircraft, or UAV
    )


def intruder_main(
    cfg: IntruderConfig,
    stop: threading.Event | None = None,
    clock_s: Callable[[], float] = time.monotonic,
    out: Callable[[str], None] = print,
) -> int:
    """Fly the line and report it until it arrives (or `stop` is set). Raises MeshUnreachable
    when nobody answers at the endpoints, ValueError (FleetKeyError...) for a bad key."""
    stop = stop or threading.Event()
    auth = load_auth(cfg.key_file, fleet=cfg.mesh.fleet)
    reporter = cfg.gcs_id
    if auth is not None:
        if auth.role is not Role.STATION:
            raise ValueError(
                f"{cfg.key_file} is {auth.key.name}'s key: a station key reports traffic"
            )
        reporter = auth.member_id
    period_s = 1.0 / cfg.rate_hz
    sent = 0
    with Mesh(cfg.mesh, auth=auth, stop=stop) as mesh:
        out(
            f"intruder {cfg.track_id:#x} ({'manned' if cfg.manned else 'unmanned'}): "
            f"{cfg.from_ne_m} -> {cfg.to_ne_m} m at {cfg.speed_m_s:g} m/s, {cfg.alt_m:g} m up, "
            f"{cfg.duration_s:.1f} s"
        )
        start_s = clock_s()
        next_s = start_s
        while not stop.is_set():
            t_s = clock_s() - start_s
            track = track_at(cfg, t_s)
            publish_report(mesh, track.report(Role.STATION, reporter, mesh.clock_ns()))
            sent += 1
            if t_s >= cfg.duration_s:
                break
            next_s += period_s
            stop.wait(max(0.0, next_s - clock_s()))
    out(f"intruder {cfg.track_id:#x}: {sent} reports sent")
    return 0


def _ne(what: str) -> Callable[[str], tuple[float, float]]:
    def parse(text: str) -> tuple[float, float]:
        n, e = floats(text, 2, what)
        return (n, e)

    parse.__name__ = "N,E in metres"
    return parse


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="covey intruder",
        description="fly one simulated vehicle that does not cooperate (straight line, no "
        "avoidance) through the fleet, reported on the mesh as traffic",
    )
    # A negative first number needs the = form (--from-ne-m=-30,0), as every covey N,E flag.
    p.add_argument(
        "--from-ne-m", required=True, type=_ne("--from-ne-m"), help="start N,E (m), e.g. =-30,0"
    )
    p.add_argument("--to-ne-m", required=True, type=_ne("--to-ne-m"), help="end N,E (m)")
    p.add_argument("--speed-m-s", type=finite("m/s"), default=2.0, help="ground speed (2)")
    p.add_argument(
        "--alt-m", type=finite("m", minimum=None), default=10.0, help="height above origin (10)"
    )
    p.add_argument("--manned", action="store_true", help="a manned aircraft (larger separation)")
    p.add_argument("--rate-hz", type=finite("Hz"), default=5.0, help="reports per second (5)")
    p.add_argument(
        "--start-delay-s",
        type=finite("seconds", inclusive=True),
        default=0.0,
        help="report from the start point this long before flying (0)",
    )
    p.add_argument("--gcs-id", type=int, default=1, help="reporting station id, open mode (1)")
    p.add_argument(
        "--track-id", type=lambda t: int(t, 0), default=DEFAULT_TRACK_ID, help="track id (32 bit)"
    )
    add_mesh_args(p)
    return p


def cli(argv: list[str] | None = None) -> int:
    p = parser()
    args = p.parse_args(sys.argv[1:] if argv is None else argv)
    try:
        cfg = IntruderConfig(
            mesh=mesh_config(args, p),
            from_ne_m=args.from_ne_m,
            to_ne_m=args.to_ne_m,
            speed_m_s=args.speed_m_s,
            alt_m=args.alt_m,
            manned=args.manned,
            rate_hz=args.rate_hz,
            gcs_id=args.gcs_id,
            track_id=args.track_id,
            key_file=key_file_path(args),
            start_delay_s=args.start_delay_s,
        )
    except ValueError as exc:
        die(p, str(exc))
    try:
        with stop_on_signals() as stop:
            return intruder_main(cfg, stop)
    except MeshUnreachable as exc:
        return nobody_answered(p, exc)
    except ValueError as exc:  # FleetKeyError, a vehicle's key
        die(p, str(exc))
