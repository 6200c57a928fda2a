"""`covey agent`: run the agent of one vehicle.

covey agent --id 3                                   # built-in simulator, embedded mesh
covey agent --id 3 --vehicle mavsdk:udpin://0.0.0.0:14543   # PX4 via MAVSDK (companion mode)
covey agent --id 3 --vehicle relay:udpin:0.0.0.0:14553      # PX4 runs the policy (onboard mode)
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import logging
import math
import signal
import sys
import threading
import time

from agent.app import Agent, AgentConfig
from agent.backends.base import VehicleBackend
from agent.failsafe import FailsafeConfig
from agent.guidance import GuidanceConfig
from comms.auth import FleetAuth, load_auth
from comms.geo import GeoOrigin
from comms.mesh import Mesh
from comms.schema import POSITION_LIMIT_M
from comms.session import DEFAULT_PORT, MeshConfig

log = logging.getLogger("covey.agent")


def make_backend(
    spec: str, cfg: AgentConfig, start_ned_m: tuple[float, float, float], clock_s
) -> VehicleBackend:
    """Build the backend named by `spec`: sim | mavsdk:<url> | relay:<url>."""
    kind, _, url = spec.partition(":")
    if kind == "sim":
        from agent.backends.sim import SimBackend, SimConfig

        return SimBackend(SimConfig(start_ned_m=start_ned_m), now_s=clock_s())
    if kind == "mavsdk":
        from agent.backends.mavsdk_backend import MavsdkBackend

        return MavsdkBackend(url or "udpin://0.0.0.0:14540", origin=cfg.origin)
    if kind == "relay":
        from agent.backends.relay import RelayBackend

        return RelayBackend(url or "udpin:0.0.0.0:14550", origin=cfg.origin)
    raise ValueError(f"unknown vehicle {spec!r}: use sim, mavsdk:<url> or relay:<url>")


def _floats(text: str, n: int, what: str) -> tuple[float, ...]:
    try:
        values = tuple(float(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"{what} must be {n} comma-separated numbers, got {text!r}"
        ) from None
    if len(values) != n or not all(v == v and abs(v) != float("inf") for v in values):
        raise argparse.ArgumentTypeError(
            f"{what} must be {n} finite comma-separated numbers, got {text!r}"
        )
    return values


def _start_ne(text: str) -> tuple[float, ...]:
    """--start: two finite numbers that a VehicleState can carry (else no state is ever sent)."""
    ne = _floats(text, 2, "--start")
    if any(abs(v) > POSITION_LIMIT_M for v in ne):
        raise argparse.ArgumentTypeError(
            f"--start {text!r}: each coordinate must be within ±{POSITION_LIMIT_M:g} m"
        )
    return ne


def add_mesh_args(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("mesh")
    g.add_argument("--fleet", default="covey", help="fleet name (default covey)")
    g.add_argument(
        "--connect",
        action="append",
        default=None,
        help=f"Zenoh endpoint to join (repeatable; default tcp/127.0.0.1:{DEFAULT_PORT})",
    )
    g.add_argument(
        "--listen",
        action="append",
        default=None,
        help="endpoint to listen on (default tcp/127.0.0.1:0)",
    )
    g.add_argument("--mesh-mode", choices=["peer", "client", "router"], default="peer")
    # A bad endpoint (port 99999) or --zenoh-config is refused in one line by MeshConfig/Mesh.
    g.add_argument(
        "--zenoh-config", default=None, help="full Zenoh JSON5 config file (TLS, auth, ACL)"
    )


def mesh_config(args: argparse.Namespace) -> MeshConfig:
    kw = {}
    if args.connect:
        kw["connect"] = tuple(args.connect)
    if args.listen:
        kw["listen"] = tuple(args.listen)
    return MeshConfig(fleet=args.fleet, mode=args.mesh_mode, config_file=args.zenoh_config, **kw)


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="covey agent",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--id", type=int, required=True, help="vehicle id, 1..65000")
    p.add_argument("--vehicle", default="sim", help="sim (default) | mavsdk:<url> | relay:<url>")
    p.add_argument(
        "--start",
        type=_start_ne,
        default=(0.0, 0.0),
        help=f"sim start position N,E in metres (each within ±{POSITION_LIMIT_M:g})",
    )
    p.add_argument(
        "--origin",
        type=lambda s: _floats(s, 3, "--origin"),
        default=None,
        help="fleet origin lat,lon,alt",
    )
    p.add_argument(
        "--link",
        default="perfect",
        help="emulated radio link: perfect | xbee | wifi | rate=3,loss=0.2,...",
    )
    p.add_argument(
        "--separation-m",
        type=float,
        default=3.0,
        help="minimum distance kept from other vehicles (default 3)",
    )
    p.add_argument(
        "--cruise-speed-m-s", type=float, default=1.0, help="speed the policy flies at (default 1)"
    )
    p.add_argument("--no-safety-filter", action="store_true", help="fly the pure learned policy")
    p.add_argument(
        "--decision-period-s",
        type=float,
        default=None,
        help="seconds between policy decisions, held in between (default: the policy's "
        "trained period, 1 s x separation/3 / cruise speed; 0: every tick)",
    )
    p.add_argument("--policy", default=None, help="policy weights (.npz); default: shipped weights")
    p.add_argument("--geofence-radius-m", type=float, default=500.0, help="0 = no fence")
    p.add_argument(
        "--gcs-lost-hold-s",
        type=float,
        default=5.0,
        help="no ground station this long: hold (default 5)",
    )
    p.add_argument(
        "--gcs-lost-land-s",
        type=float,
        default=30.0,
        help="no ground station this long: land (default 30)",
    )
    p.add_argument(
        "--no-gcs-failsafe", action="store_true", help="keep flying without a ground station"
    )
    p.add_argument("--tick-hz", type=float, default=10.0, help="guidance loop rate (default 10)")
    p.add_argument(
        "--state-hz", type=float, default=10.0, help="state broadcast rate on the mesh (default 10)"
    )
    p.add_argument("--duration-s", type=float, default=None, help="exit after this long (tests)")
    p.add_argument(
        "--trace-guidance",
        action="store_true",
        help="publish guidance traces so `covey replay --policy` can replay the flight exactly",
    )
    p.add_argument("-v", "--verbose", action="store_true", help="log at INFO level")
    p.add_argument(
        "--key-file",
        default=None,
        help="this vehicle's key file (covey keygen add vehicle N); or $COVEY_FLEET_KEY_FILE. "
        "Without one the agent runs in OPEN MODE (nothing authenticated; tests only)",
    )
    add_mesh_args(p)
    return p


def config_from_args(args: argparse.Namespace) -> AgentConfig:
    return AgentConfig(
        vehicle_id=args.id,
        mesh=mesh_config(args),
        tick_hz=args.tick_hz,
        state_hz=args.state_hz,
        origin=GeoOrigin(*args.origin) if args.origin else GeoOrigin(),
        guidance=GuidanceConfig(
            separation_m=args.separation_m,
            cruise_speed_m_s=args.cruise_speed_m_s,
            safety_filter=not args.no_safety_filter,
            policy_path=args.policy,
            decision_period_s=args.decision_period_s,
        ),
        failsafe=FailsafeConfig(
            require_gcs=not args.no_gcs_failsafe,
            gcs_lost_hold_s=args.gcs_lost_hold_s,
            gcs_lost_land_s=args.gcs_lost_land_s,
            geofence_radius_m=args.geofence_radius_m,
        ),
        link=args.link,
        trace_guidance=args.trace_guidance,
    )


def make_link(spec: str, vehicle_id: int, receiver_pos=None):
    """The emulated radio between this agent and its neighbours, or None for a perfect link."""
    if spec in ("", "perfect"):
        return None
    from comms import link

    return link.emulator_from_spec(
        spec, seed=vehicle_id, receiver_pos=receiver_pos, own_id=vehicle_id
    )


def main(
    cfg: AgentConfig,
    vehicle: str = "sim",
    start_ne_m=(0.0, 0.0),
    stop: threading.Event | None = None,
    duration_s: float | None = None,
    auth: FleetAuth | None = None,
) -> int:
    stop = stop or threading.Event()
    clock_s = time.monotonic
    with contextlib.ExitStack() as stack:
        backend = stack.enter_context(
            make_backend(vehicle, cfg, (start_ne_m[0], start_ne_m[1], 0.0), clock_s)
        )
        mesh = stack.enter_context(Mesh(cfg.mesh, auth=auth))
        own_pos: list = [None]  # filled once the agent exists; range-dependent loss needs it
        link = make_link(cfg.link, cfg.vehicle_id, receiver_pos=lambda: own_pos[0])
        if link is not None:
            link = stack.enter_context(link)
        agent = Agent(cfg, backend, mesh, clock_s=clock_s, link=link)
        own_pos[0] = None
        agent.on_position = lambda p: own_pos.__setitem__(0, p)
        log.info(
            "vehicle %d up: fleet %s, %s, link %s",
            cfg.vehicle_id,
            cfg.mesh.fleet,
            vehicle,
            cfg.link,
        )
        timer = threading.Timer(duration_s, stop.set) if duration_s is not None else None
        if timer is not None:
            timer.daemon = True
            timer.start()
        try:
            agent.run(stop)
        finally:
            if timer is not None:
                timer.cancel()
    return 0


def cli(argv: list[str]) -> int:
    p = parser()
    args = p.parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING,
        format="%(asctime)s %(name)s %(levelname)s %(message)s",
    )
    if args.duration_s is not None and not (math.isfinite(args.duration_s) and args.duration_s > 0):
        p.error(f"--duration-s must be a positive number of seconds, got {args.duration_s}")
    try:
        cfg = config_from_args(args)
    except ValueError as exc:
        _die(str(exc))
    try:
        auth = load_auth(args.key_file, fleet=cfg.mesh.fleet)
    except ValueError as exc:  # FleetKeyError: empty path, unreadable, malformed, wrong fleet
        _die(str(exc))
    if auth is not None and not (auth.role.name == "VEHICLE" and auth.member_id == cfg.vehicle_id):
        _die(f"--key-file is {auth.key.name}'s key, not vehicle {cfg.vehicle_id}'s")
    cfg = dataclasses.replace(cfg, open_mode=auth is None)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    try:
        return main(
            cfg,
            vehicle=args.vehicle,
            start_ne_m=args.start,
            stop=stop,
            duration_s=args.duration_s,
            auth=auth,
        )
    except (ValueError, FileNotFoundError) as exc:  # MeshConfigError: bad --zenoh-config, busy port
        _die(str(exc))
    return 2


def _die(message: str) -> int:
    """A set-up error: one line on stderr, exit status 2, no traceback."""
    print(f"covey agent: error: {' '.join(message.split())}", file=sys.stderr)
    raise SystemExit(2)
