"""`covey sitl`: parse the command line into a SitlConfig and run the emulator."""

from __future__ import annotations

import argparse
import logging
from collections.abc import Sequence

from cli.options import (
    add_config_flags,
    config_from_flags,
    finite,
    geo_origin,
    given,
    renamed,
    setup_logging,
    stop_on_signals,
    unit_of,
)
from comms.geo import GeoOrigin
from firmware.sitl.config import SitlConfig
from firmware.sitl.params import VehicleParams
from policy.pointmass import vehicle_model_arg

PARAM_FLAGS = (
    "cruise_speed_m_s",
    "takeoff_speed_m_s",
    "land_speed_m_s",
    "climb_speed_m_s",
    "descent_speed_m_s",
    "pos_gain_1_s",
    "accel_m_s2",
    "disarm_after_land_s",
)
"""The airframe settings a command line may change (flag = field name, unit included)."""
CONFIG_FLAGS = (
    "onboard",
    "separation_m",
    "policy_separation_m",
    "policy_speed_m_s",
    "sparse_rule",
    "duration_s",
)
ONBOARD_ONLY = ("weights", "separation_m", "policy_separation_m", "policy_speed_m_s", "sparse_rule")
"""Settings of the onboard C policy: refused without --onboard, where nothing would read them."""
RENAMED = {
    "--separation": "--separation-m",
    "--policy-speed": "--policy-speed-m-s",
    "--cruise-speed": "--cruise-speed-m-s",
    "--takeoff-speed": "--takeoff-speed-m-s",
    "--land-speed": "--land-speed-m-s",
    "--climb-speed": "--climb-speed-m-s",
    "--descent-speed": "--descent-speed-m-s",
    "--pos-gain": "--pos-gain-1-s",
    "--accel": "--accel-m-s2",
    "--disarm-after-land": "--disarm-after-land-s",
    "--duration": "--duration-s",
}


def _positive(name: str):
    return finite(unit_of(name) or "units")


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
        "--home",
        type=geo_origin,
        default=GeoOrigin(),
        metavar="LAT,LON,ALT",
        help="boot position in degrees, degrees, metres",
    )
    p.add_argument(
        "--weights", default=None, help="C policy weights (onboard mode; default: shipped)"
    )
    p.add_argument(
        "--unhealthy", action="store_true", help="emulate a failed sensor: arming is refused"
    )
    p.add_argument(
        "--vehicle-model",
        type=vehicle_model_arg,
        default="ideal",
        metavar="MODEL",
        help="ideal: the setpoint within MPC_ACC_HOR, exact positions; realistic: 0.3 s lag, "
        "0.2 m/s gusts, GNSS drifting 0.5 m (reported, with its sigma as GPS_RAW_INT h_acc); "
        "fields changed after a colon: realistic:drift_m=1.0 (policy.pointmass.VehicleModel)",
    )
    add_config_flags(
        p,
        SitlConfig,
        only=CONFIG_FLAGS,
        types={n: _positive(n) for n in CONFIG_FLAGS if n not in ("onboard", "sparse_rule")},
    )
    g = p.add_argument_group("airframe (PX4 parameter names in brackets)")
    add_config_flags(
        g, VehicleParams, only=PARAM_FLAGS, types={n: _positive(n) for n in PARAM_FLAGS}
    )
    renamed(p, RENAMED)
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
    return config_from_flags(
        SitlConfig,
        a,
        only=CONFIG_FLAGS,
        vehicle_id=a.id,
        links=tuple(links),
        home=a.home,
        vehicle_model=a.vehicle_model,
        policy_weights=a.weights,
        healthy=not a.unhealthy,
        params=config_from_flags(VehicleParams, a, only=PARAM_FLAGS),
    )


def cli(argv: Sequence[str] | None = None) -> int:
    p = parser()
    args = p.parse_args(argv)
    if not args.onboard and (flags := given(p, args, *ONBOARD_ONLY)):
        p.error(f"{', '.join(flags)}: settings of the onboard policy, which needs --onboard")
    try:
        cfg = _config(args)
    except ValueError as exc:
        p.error(str(exc))
    setup_logging(args.verbose, quiet_level=logging.INFO, name="sitl")
    from firmware.sitl.emulator import main  # after parsing: --help stays fast

    with stop_on_signals() as stop:
        try:
            main(cfg, stop)
        except (OSError, RuntimeError) as exc:
            logging.getLogger(__name__).error("sitl failed: %s", exc)
            return 1
    return 0
