"""`covey sitl`: parse the command line into a SitlConfig and run the emulator."""

from __future__ import annotations

import argparse
import logging
import signal
import threading
from collections.abc import Sequence

from comms.geo import GeoOrigin
from firmware.sitl.config import SitlConfig
from firmware.sitl.params import VehicleParams


def _home(text: str) -> GeoOrigin:
    try:
        lat, lon, alt = (float(x) for x in text.split(","))
        return GeoOrigin(lat, lon, alt)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(
            f"--home must be LAT,LON,ALT in degrees and metres: {exc}"
        ) from exc


def _positive(text: str) -> float:
    value = float(text)
    if not value > 0.0:
        raise argparse.ArgumentTypeError(f"must be positive, got {text}")
    return value


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="covey sitl",
        description="PX4-compatible MAVLink autopilot emulator "
        "(point-mass multicopter) that MAVSDK and the covey relay can fly.",
    )
    p.add_argument("--id", type=int, default=1, help="MAVLink system id / vehicle id (1..254)")
    p.add_argument(
        "--connect",
        action="append",
        default=[],
        metavar="udpout:HOST:PORT",
        help="send to a listener, e.g. MAVSDK's udpin://0.0.0.0:14540 (repeatable)",
    )
    p.add_argument(
        "--listen",
        action="append",
        default=[],
        metavar="udpin:HOST:PORT",
        help="listen and answer whoever speaks (repeatable)",
    )
    p.add_argument(
        "--home", type=_home, default=GeoOrigin(), metavar="LAT,LON,ALT", help="boot position"
    )
    p.add_argument(
        "--onboard",
        action="store_true",
        help="fly goto targets with the C policy, avoiding traffic",
    )
    p.add_argument(
        "--weights", default=None, help="C policy weights (onboard mode; default: shipped)"
    )
    p.add_argument(
        "--separation",
        type=_positive,
        default=3.0,
        help="m kept from traffic by the onboard policy",
    )
    p.add_argument(
        "--policy-speed", type=_positive, default=1.0, help="m/s cruise of the onboard policy"
    )
    p.add_argument(
        "--unhealthy", action="store_true", help="emulate a failed sensor: arming is refused"
    )
    defaults = VehicleParams()
    p.add_argument(
        "--cruise-speed",
        type=_positive,
        default=defaults.cruise_speed_m_s,
        help="m/s (MPC_XY_CRUISE)",
    )
    p.add_argument(
        "--takeoff-speed",
        type=_positive,
        default=defaults.takeoff_speed_m_s,
        help="m/s (MPC_TKO_SPEED)",
    )
    p.add_argument(
        "--land-speed", type=_positive, default=defaults.land_speed_m_s, help="m/s (MPC_LAND_SPEED)"
    )
    p.add_argument(
        "--climb-speed",
        type=_positive,
        default=defaults.climb_speed_m_s,
        help="m/s (MPC_Z_VEL_MAX_UP)",
    )
    p.add_argument(
        "--descent-speed",
        type=_positive,
        default=defaults.descent_speed_m_s,
        help="m/s (MPC_Z_VEL_MAX_DN)",
    )
    p.add_argument(
        "--pos-gain",
        type=_positive,
        default=defaults.pos_gain_1_s,
        help="1/s position loop gain (MPC_XY_P)",
    )
    p.add_argument(
        "--accel", type=_positive, default=defaults.accel_m_s2, help="m/s^2 (MPC_ACC_HOR)"
    )
    p.add_argument(
        "--disarm-after-land",
        type=_positive,
        default=defaults.disarm_after_land_s,
        help="s (COM_DISARM_LAND)",
    )
    p.add_argument("--duration", type=_positive, default=None, help="stop after this many seconds")
    p.add_argument("-v", "--verbose", action="store_true")
    return p


def config_from_args(argv: Sequence[str] | None = None) -> SitlConfig:
    """Parse a `covey sitl` command line into its config (argparse exits on bad input)."""
    return _config(parser().parse_args(argv))


def _config(a: argparse.Namespace) -> SitlConfig:
    links = [*a.connect, *(u if u.startswith("udpin") else f"udpin:{u}" for u in a.listen)]
    links = [u if u.startswith("udp") else f"udpout:{u}" for u in links] or [
        "udpout:127.0.0.1:14540"
    ]
    params = VehicleParams(
        cruise_speed_m_s=a.cruise_speed,
        takeoff_speed_m_s=a.takeoff_speed,
        land_speed_m_s=a.land_speed,
        climb_speed_m_s=a.climb_speed,
        descent_speed_m_s=a.descent_speed,
        accel_m_s2=a.accel,
        pos_gain_1_s=a.pos_gain,
        disarm_after_land_s=a.disarm_after_land,
    )
    return SitlConfig(
        vehicle_id=a.id,
        links=tuple(links),
        home=a.home,
        onboard=a.onboard,
        policy_weights=a.weights,
        separation_m=a.separation,
        policy_speed_m_s=a.policy_speed,
        healthy=not a.unhealthy,
        params=params,
        duration_s=a.duration,
    )


def cli(argv: Sequence[str] | None = None) -> int:
    args = parser().parse_args(argv)
    try:
        cfg = _config(args)
    except ValueError as exc:
        parser().error(str(exc))
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s sitl %(levelname)s %(message)s",
    )
    from firmware.sitl.app import main  # after parsing: --help stays fast

    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    try:
        main(cfg, stop)
    except (OSError, RuntimeError) as exc:
        logging.getLogger(__name__).error("sitl failed: %s", exc)
        return 1
    return 0
