"""`covey agent`: run the agent of one vehicle, or of many simulated vehicles in one process.

covey agent --id 3 --start-ne-m 0,6                  # built-in simulator
covey agent --id 3 --vehicle mavsdk:udpin://0.0.0.0:14543   # PX4 via MAVSDK (companion mode)
covey agent --id 3 --vehicle relay:udpin:0.0.0.0:14553      # PX4 runs the policy (onboard mode)
covey agent --ids 1-100 --key-dir keys/              # a host of 100 simulated vehicles

With --ids, one process hosts those vehicles (simulated; a real autopilot is one per process):
each runs the same flight core as a single agent, with its own identity (its own key from
--key-dir DIR/vehicle-<id>.key), state, presence, events and command queryable, so one fleet
can mix single agents and hosts (agent/fleet_sim.py, docs/scaling.md).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import logging
import math
import os
import threading
import time

from agent.app import Agent, AgentConfig
from agent.backends.base import VehicleBackend
from agent.failsafe import FailsafeConfig
from agent.guidance import GuidanceConfig
from agent.returning import ReturnConfig
from cli.options import (
    add_config_flags,
    add_mesh_args,
    config_from_flags,
    die,
    floats,
    geo_origin,
    given,
    mesh_config,
    renamed,
    setup_logging,
    stop_after,
    stop_on_signals,
    vehicle_ids,
)
from comms.geo import GeoOrigin
from comms.mesh import Mesh
from comms.schema import POSITION_LIMIT_M
from comms.state_rate import IDLE_STATE_HZ, MAX_IDLE_PERIOD_S, MIN_STEADY_STATE_HZ, SteadyConfig
from trust.auth import ENV_KEY_FILE, FleetAuth, load_auth, load_vehicle_auths

log = logging.getLogger("covey.agent")


def make_backend(
    spec: str,
    cfg: AgentConfig,
    start_ned_m: tuple[float, float, float],
    clock_s,
    vehicle_model: str = "ideal",
) -> VehicleBackend:
    """Build the backend named by `spec`: sim | mavsdk:<url> | relay:<url>; a simulated one
    flies `vehicle_model` (`sim_config`)."""
    kind, _, url = spec.partition(":")
    if kind == "sim":
        from agent.backends.sim import SimBackend

        return SimBackend(sim_config(vehicle_model, start_ned_m=start_ned_m), now_s=clock_s())
    if kind == "mavsdk":
        from agent.backends.mavsdk_backend import MavsdkBackend

        return MavsdkBackend(url or "udpin://0.0.0.0:14540", origin=cfg.origin)
    if kind == "relay":
        from agent.backends.relay import RelayBackend

        return RelayBackend(url or "udpin:0.0.0.0:14550", origin=cfg.origin)
    raise ValueError(f"unknown vehicle {spec!r}: use sim, mavsdk:<url> or relay:<url>")


def _start_ne(text: str) -> tuple[float, ...]:
    """--start-ne-m: two finite numbers that a VehicleState can carry (else no state is ever
    sent)."""
    ne = floats(text, 2, "--start-ne-m")
    if any(abs(v) > POSITION_LIMIT_M for v in ne):
        raise argparse.ArgumentTypeError(
            f"--start-ne-m {text!r}: each coordinate must be within ±{POSITION_LIMIT_M:g} m"
        )
    return ne


GUIDANCE_FLAGS = (
    "policy",
    "no_safety_filter",
    "decision_period_s",
    "trace_guidance",
    "policy_separation_m",
    "sparse_rule",
)
"""Flags for the agent's own guidance, which a relay vehicle (the policy runs onboard) lacks."""
HOST_FLAGS = ("spacing_m", "max_neighbours", "no_see_others")
"""Flags of the multi-vehicle host (--ids) only."""
SINGLE_FLAGS = {
    "link": "per-vehicle radio links are emulated by a single agent (--id) only",
    "state_hz": "a host publishes every vehicle's state each tick: set --tick-hz",
    "trace_guidance": "guidance traces come from a single agent (--id) only",
    "plan": "a host follows the fleet plan on the mesh; --plan starts a single agent with one",
    "key_file": "a key file signs for one vehicle; give --key-dir DIR with vehicle-<id>.key "
    "for each",
}
"""Flags of a single agent (--id) only, and why a host (--ids) refuses them."""


def sim_config(vehicle_model: str, **kw):
    """The simulator's config for --vehicle-model: ideal = the simulator as it always was (it
    flies the setpoint with SimConfig's acceleration limit and knows where it is), realistic =
    policy.pointmass.VehicleModel.realistic() (0.3 s lag, 2.5 m/s^2, gusts, 0.5 m GNSS drift)."""
    from agent.backends.sim import SimConfig
    from policy.pointmass import VehicleModel

    model = None if vehicle_model == "ideal" else VehicleModel.named(vehicle_model)
    return SimConfig(vehicle=model, **kw)


def add_flight_args(
    p: argparse.ArgumentParser, *, geofence_radius_m: float = 500.0, gcs_failsafe: bool = True
) -> None:
    """The flags every shell of the flight core shares (`covey agent`, one vehicle or many, and
    `covey fleet-sim`): start position, fleet origin, guidance, geofence, the ground-station
    failsafe (unless `gcs_failsafe` is False: fleet-sim flies without one), run time, logging."""
    p.add_argument(
        "--vehicle-model",
        choices=("ideal", "realistic"),
        default="ideal",
        help="how simulated vehicles fly: ideal (exactly the setpoint within the acceleration "
        "limit, exact positions) or realistic (0.3 s velocity lag, 2.5 m/s^2, 0.2 m/s gusts, "
        "GNSS estimate drifting 0.5 m: they report the estimate and its sigma); sim only",
    )
    p.add_argument(
        "--start-ne-m",
        type=_start_ne,
        default=(0.0, 0.0),
        metavar="N,E",
        help=f"sim start position north,east in metres (each within ±{POSITION_LIMIT_M:g}; "
        "sim only: a real vehicle is where it is); with --ids the start grid's corner",
    )
    renamed(p, {"--start": "--start-ne-m"})
    p.add_argument(
        "--origin",
        type=geo_origin,
        default=None,
        metavar="LAT,LON,ALT",
        help="fleet origin in degrees, degrees, metres (default: covey's)",
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
    p.add_argument(
        "--no-safety-filter",
        action="store_true",
        help="fly the pure learned policy (sim and mavsdk: a relay vehicle runs its own)",
    )
    p.add_argument(
        "--decision-period-s",
        type=float,
        default=None,
        help="seconds between policy decisions, held in between (default: the policy's "
        "trained period, 1 s x separation/3 / cruise speed; 0: every tick)",
    )
    p.add_argument("--policy", default=None, help="policy weights (.npz); default: shipped weights")
    add_config_flags(
        p,
        GuidanceConfig,
        only=(
            "policy_separation_m",
            "sparse_rule",
            "non_cooperative_separation_m",
            "manned_separation_m",
        ),
    )
    p.add_argument(
        "--geofence-radius-m",
        type=float,
        default=geofence_radius_m,
        help=f"0 = no fence (default {geofence_radius_m:g})",
    )
    add_config_flags(p, ReturnConfig)  # return layers and landing order (agent/returning.py)
    p.add_argument(
        "--no-coordinated-return",
        action="store_true",
        help="return home at its own altitude and land as it arrives (--return-layer-m 0 "
        "--land-radius-m 0); default: on its layer, landing one at a time",
    )
    if gcs_failsafe:
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
    p.add_argument(
        "--idle-state-hz",
        type=float,
        default=IDLE_STATE_HZ,
        help=f"state rate while landed, disarmed and idle (default {IDLE_STATE_HZ:g}, at least "
        f"{1 / MAX_IDLE_PERIOD_S:g}; full rate again from the tick after a command)",
    )
    p.add_argument(
        "--steady-state-hz",
        type=float,
        default=None,
        help=f"state rate in the air while the last state still predicts this vehicle (within "
        f"0.1 m, 0.1 m/s, 0.05 rad; hovering, flying straight), at least "
        f"{MIN_STEADY_STATE_HZ:g}; default: off, always the full rate (comms/state_rate.py)",
    )
    p.add_argument("--duration-s", type=float, default=None, help="exit after this long (tests)")
    p.add_argument("-v", "--verbose", action="store_true", help="log at INFO level")


def add_host_args(p: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    """The flags of a host of many simulated vehicles (`covey agent --ids`, `covey fleet-sim`)."""
    p.add_argument(
        "--spacing-m", type=float, default=8.0, help="start grid spacing in metres (default 8)"
    )
    p.add_argument(
        "--max-neighbours",
        type=int,
        default=10,
        help="nearest neighbours per policy call (default 10)",
    )
    p.add_argument(
        "--no-see-others", action="store_true", help="ignore vehicles of other processes"
    )


def guidance_from_args(args: argparse.Namespace) -> GuidanceConfig:
    return GuidanceConfig(
        separation_m=args.separation_m,
        cruise_speed_m_s=args.cruise_speed_m_s,
        safety_filter=not args.no_safety_filter,
        policy_path=args.policy,
        decision_period_s=args.decision_period_s,
        policy_separation_m=args.policy_separation_m,
        sparse_rule=args.sparse_rule,
        non_cooperative_separation_m=args.non_cooperative_separation_m,
        manned_separation_m=args.manned_separation_m,
    )


def steady_from_args(args: argparse.Namespace) -> SteadyConfig | None:
    """The steady-rate rule from --steady-state-hz (None: off); a bad rate raises ValueError."""
    hz = args.steady_state_hz
    return None if hz is None else SteadyConfig(state_hz=hz)


def failsafe_from_args(args: argparse.Namespace) -> FailsafeConfig:
    """The failsafes the flags ask for; without the ground-station flags (fleet-sim), none.
    --no-coordinated-return with a layer or radius flag raises ValueError (one of them would
    be ignored)."""
    returning = config_from_flags(ReturnConfig, args)
    if args.no_coordinated_return:
        default = ReturnConfig()
        if (returning.return_layer_m, returning.land_radius_m) != (
            default.return_layer_m,
            default.land_radius_m,
        ):
            raise ValueError(
                "--no-coordinated-return turns the layers and the landing order off: "
                "drop --return-layer-m / --land-radius-m"
            )
        returning = dataclasses.replace(returning, return_layer_m=0.0, land_radius_m=0.0)
    if not hasattr(args, "no_gcs_failsafe"):
        return FailsafeConfig(
            require_gcs=False, geofence_radius_m=args.geofence_radius_m, returning=returning
        )
    return FailsafeConfig(
        require_gcs=not args.no_gcs_failsafe,
        gcs_lost_hold_s=args.gcs_lost_hold_s,
        gcs_lost_land_s=args.gcs_lost_land_s,
        geofence_radius_m=args.geofence_radius_m,
        returning=returning,
    )


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="covey agent",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    who = p.add_mutually_exclusive_group(required=True)
    who.add_argument("--id", type=int, help="vehicle id, 1..65000")
    who.add_argument(
        "--ids",
        type=vehicle_ids,
        metavar="IDS",
        help="host these simulated vehicles in one process: ids and ranges, e.g. 1-100 or "
        "1-50,60,70-79",
    )
    p.add_argument("--vehicle", default="sim", help="sim (default) | mavsdk:<url> | relay:<url>")
    add_flight_args(p)
    p.add_argument(
        "--link",
        default="perfect",
        help="emulated radio link: perfect | xbee | wifi | rate=3,loss=0.2,...",
    )
    p.add_argument("--tick-hz", type=float, default=10.0, help="guidance loop rate (default 10)")
    p.add_argument(
        "--state-hz", type=float, default=10.0, help="state broadcast rate on the mesh (default 10)"
    )
    p.add_argument(
        "--plan",
        default=None,
        metavar="FILE",
        help="a signed fleet plan to hold from start (covey plan load writes plan.bin): fence "
        "and keep-out zones apply before any station is reachable; a newer one on the mesh "
        "replaces it",
    )
    p.add_argument(
        "--trace-guidance",
        action="store_true",
        help="publish guidance traces so `covey replay --policy` can replay the flight exactly",
    )
    add_host_args(p.add_argument_group("multi-vehicle host (--ids only)"))
    # --key-file: this vehicle's (covey keygen add vehicle N); --key-dir: vehicle-<id>.key each
    add_mesh_args(p, key_dir=True)
    return p


def config_from_args(
    args: argparse.Namespace, p: argparse.ArgumentParser | None = None
) -> AgentConfig:
    """The agent's config; a bad value raises ValueError (or, given the parser, exits 2)."""
    return AgentConfig(
        vehicle_id=args.id,
        mesh=mesh_config(args, p),
        tick_hz=args.tick_hz,
        state_hz=args.state_hz,
        idle_state_hz=args.idle_state_hz,
        steady=steady_from_args(args),
        origin=args.origin or GeoOrigin(),
        guidance=guidance_from_args(args),
        failsafe=failsafe_from_args(args),
        link=args.link,
        trace_guidance=args.trace_guidance,
        plan=signed_plan(args.plan),
    )


def signed_plan(path: str | None):
    """The signed fleet plan in `path` (comms/plan_io.py; shapely is imported only then), or
    None; BadPlanError (a ValueError, one line) if it cannot be used."""
    if path is None:
        return None
    from comms.plan_io import read_signed_plan

    return read_signed_plan(path)


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
    vehicle_model: str = "ideal",
) -> int:
    stop = stop or threading.Event()
    clock_s = time.monotonic
    # The duration bounds the whole run, waiting for a router included.
    with contextlib.ExitStack() as stack, stop_after(duration_s, stop):
        backend = stack.enter_context(
            make_backend(vehicle, cfg, (start_ne_m[0], start_ne_m[1], 0.0), clock_s, vehicle_model)
        )
        mesh = stack.enter_context(Mesh(cfg.mesh, auth=auth, stop=stop))
        own_pos: list = [None]  # filled once the agent exists; range-dependent loss needs it
        link = make_link(cfg.link, cfg.vehicle_id, receiver_pos=lambda: own_pos[0])
        if link is not None:
            link = stack.enter_context(link)
        agent = stack.enter_context(Agent(cfg, backend, mesh, clock_s=clock_s, link=link))
        own_pos[0] = None
        agent.on_position = lambda p: own_pos.__setitem__(0, p)
        log.info(
            "vehicle %d up: fleet %s, %s, link %s",
            cfg.vehicle_id,
            cfg.mesh.fleet,
            vehicle,
            cfg.link,
        )
        agent.run(stop)
    return 0


def check_duration(p: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    if args.duration_s is not None and not (math.isfinite(args.duration_s) and args.duration_s > 0):
        p.error(f"--duration-s must be a positive number of seconds, got {args.duration_s}")


def cli(argv: list[str]) -> int:
    p = parser()
    args = p.parse_args(argv)
    setup_logging(args.verbose)
    check_duration(p, args)
    if args.ids is not None:
        from agent.host_cli import run_agent_host

        return run_agent_host(p, args)
    if flags := given(p, args, *HOST_FLAGS):
        p.error(f"{', '.join(flags)}: a multi-vehicle host's (--ids), not a single agent's")
    kind = args.vehicle.partition(":")[0]
    if kind != "sim" and given(p, args, "start_ne_m"):
        p.error(f"--start-ne-m places a simulated vehicle; a {kind} vehicle is where it is")
    if kind != "sim" and given(p, args, "vehicle_model"):
        p.error(f"--vehicle-model is how a simulated vehicle flies; a {kind} vehicle flies itself")
    if kind == "relay" and (flags := given(p, args, *GUIDANCE_FLAGS)):
        p.error(
            f"{', '.join(flags)}: a relay vehicle runs the policy onboard (covey sitl "
            "--onboard --weights), not in the agent"
        )
    try:
        cfg = config_from_args(args, p)
        cfg.mesh.zenoh_config()  # a bad --zenoh-config is refused before anything starts
    except ValueError as exc:
        die(p, str(exc))
    auths = load_keys(p, args, (cfg.vehicle_id,), cfg.mesh.fleet)
    auth = auths[cfg.vehicle_id] if auths is not None else None
    cfg = dataclasses.replace(cfg, open_mode=auth is None)
    with stop_on_signals() as stop:
        try:
            return main(
                cfg,
                vehicle=args.vehicle,
                start_ne_m=args.start_ne_m,
                stop=stop,
                duration_s=args.duration_s,
                auth=auth,
                vehicle_model=args.vehicle_model,
            )
        except (ValueError, FileNotFoundError) as exc:  # MeshConfigError: bad config, busy port
            die(p, str(exc))


def load_keys(
    p: argparse.ArgumentParser, args: argparse.Namespace, ids: tuple[int, ...], fleet: str
) -> dict[int, FleetAuth] | None:
    """Each vehicle's FleetAuth from --key-dir (or, for one vehicle, --key-file or
    $COVEY_FLEET_KEY_FILE), or None for open mode (said loudly). A key that is configured but
    unusable, or that is another member's, exits 2 with the reason: never open mode by mistake."""
    try:
        if args.key_dir is not None:
            if args.key_file is not None:
                die(p, "--key-file and --key-dir: give one (a directory: vehicle-<id>.key each)")
            return load_vehicle_auths(args.key_dir, ids, fleet=fleet)
        if len(ids) > 1 or args.ids is not None:
            if args.key_file is not None:
                die(p, f"--key-file is refused with --ids: {SINGLE_FLAGS['key_file']}")
            if os.environ.get(ENV_KEY_FILE):
                die(
                    p,
                    f"${ENV_KEY_FILE} names one vehicle's key, and --ids hosts several: give "
                    "--key-dir DIR with vehicle-<id>.key for each (or unset it for open mode)",
                )
        auth = load_auth(args.key_file, fleet=fleet)
    except ValueError as exc:  # FleetKeyError: empty path, unreadable, malformed, wrong fleet
        die(p, str(exc))
    if auth is None:
        return None
    if not (auth.role.name == "VEHICLE" and auth.member_id == ids[0]):
        die(p, f"--key-file is {auth.key.name}'s key, not vehicle {ids[0]}'s")
    return {ids[0]: auth}
