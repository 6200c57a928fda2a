"""`covey agent` and `covey fleet-sim`: run the vehicle shell for one vehicle or many.

covey agent --id 3 --start-ne-m 0,6                  # built-in simulator
covey agent --id 3 --vehicle mavsdk:udpin://0.0.0.0:14543   # PX4 via MAVSDK (companion mode)
covey agent --id 3 --vehicle relay:udpin:0.0.0.0:14553      # PX4 runs the policy onboard
covey agent --ids 1-100 --key-dir keys/              # a host of 100 simulated vehicles
covey fleet-sim --vehicles 500 --connect tcp/127.0.0.1:7447  # open mode, for scale tests

`--id 3` is `--ids 3`: one process runs the shell (agent/shell.py) for its vehicles, each with
its own identity (its own key from --key-dir DIR/vehicle-<id>.key, or --key-file for one),
state, presence, events and command queryable, so one fleet can mix processes of one vehicle
and of many (docs/scaling.md). Several vehicles are simulated; a real autopilot is one per
process. `covey fleet-sim` is the open-mode alias for scale tests and benches: ids from
--vehicles and --first-id, no ground-station failsafe, a 2 km geofence, nothing signed.

Most flags are the fields of the config dataclasses (agent/shell_config.py, GuidanceConfig,
FailsafeConfig, ReturnConfig), with their defaults and documentation; this module only parses
them and calls `main(cfg)`.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import logging
import math
import os
import threading
import time
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING

from agent.backends.base import VehicleBackend
from agent.backends.sim import SimConfig
from agent.failsafe import FailsafeConfig
from agent.guidance import GuidanceConfig
from agent.hosts import Agent, Fleet
from agent.returning import ReturnConfig
from agent.shell import VehicleShell
from agent.shell_config import ShellConfig
from cli.options import (
    add_config_flags,
    add_mesh_args,
    config_from_flags,
    die,
    floats,
    geo_origin,
    given,
    id_ranges,
    key_env_note,
    mesh_config,
    refuse,
    renamed,
    setup_logging,
    stop_after,
    stop_on_signals,
    vehicle_ids,
)
from comms.geo import GeoOrigin
from comms.mesh import Mesh
from comms.plan import FleetPlan
from comms.schema import POSITION_LIMIT_M
from comms.session import AGENT_RUNTIME, ONE_THREAD_RUNTIME, use_zenoh_runtime
from comms.state_rate import (
    HOLD_REST_M_S,
    MAX_HOLD_PERIOD_S,
    MIN_STEADY_STATE_HZ,
    SteadyConfig,
)
from policy.pointmass import vehicle_model_arg
from trust.auth import ENV_KEY_FILE, FleetAuth, load_auth, load_vehicle_auths

if TYPE_CHECKING:  # the link emulator is imported only when one is asked for
    from comms.link import LinkEmulator

log = logging.getLogger("covey.agent")

GUIDANCE_FIELDS = (
    "separation_m",
    "cruise_speed_m_s",
    "safety_filter",
    "decision_period_s",
    "policy_path",
    "policy_separation_m",
    "sparse_rule",
    "non_cooperative_separation_m",
    "manned_separation_m",
    "c_core",
)
"""GuidanceConfig's fields that are flags (the others are tuning for code, not for users)."""
GUIDANCE_FLAGS = (
    "policy_path",
    "safety_filter",
    "decision_period_s",
    "trace_guidance",
    "policy_separation_m",
    "sparse_rule",
    "c_core",
)
"""Flags for the shell's own guidance, which a relay vehicle (the policy runs onboard) lacks."""
HOST_FLAGS = ("spacing_m", "max_neighbours", "see_others")
"""Flags of several simulated vehicles (--ids) only."""
SINGLE_FLAGS = {
    "link": "per-vehicle radio links are emulated by a single agent (--id) only",
    "state_hz": "a host publishes every vehicle's state each tick: set --tick-hz",
    "trace_guidance": "guidance traces come from a single agent (--id) only",
    "plan": "a host follows the fleet plan on the mesh; --plan starts a single agent with one",
    "key_file": "a key file signs for one vehicle; give --key-dir DIR with vehicle-<id>.key "
    "for each",
}
"""Flags of a single agent (--id) only, and why a host (--ids) refuses them."""
NO_KEY_REASON = (
    "fleet-sim is the open-mode host for scale tests: to sign, run covey agent --ids "
    "with --key-dir (one key per vehicle)"
)


# -- flags -------------------------------------------------------------------------------------------
def _start_ne(text: str) -> tuple[float, ...]:
    """--start-ne-m: two finite numbers that a VehicleState can carry (else no state is ever
    sent)."""
    ne = floats(text, 2, "--start-ne-m")
    if any(abs(v) > POSITION_LIMIT_M for v in ne):
        raise argparse.ArgumentTypeError(
            f"--start-ne-m {text!r}: each coordinate must be within ±{POSITION_LIMIT_M:g} m"
        )
    return ne


def add_flight_args(
    p: argparse.ArgumentParser, *, geofence_radius_m: float = 500.0, gcs_failsafe: bool = True
) -> None:
    """The flags every run of the shell shares (`covey agent`, one vehicle or many, and `covey
    fleet-sim`): start position, fleet origin, guidance, geofence, the ground-station failsafe
    (unless `gcs_failsafe` is False: fleet-sim flies without one), state rates, run time."""
    p.add_argument(
        "--vehicle-model",
        type=vehicle_model_arg,
        default="ideal",
        metavar="MODEL",
        help="how simulated vehicles fly: ideal (exactly the setpoint within the acceleration "
        "limit, exact positions) or realistic (0.3 s velocity lag, 2.5 m/s^2, 0.2 m/s gusts, "
        "GNSS estimate drifting 0.5 m: they report the estimate and its sigma), optionally "
        "with fields changed (realistic:drift_m=1.0,gust_m_s=0.4: policy.pointmass."
        "VehicleModel); sim only",
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
    add_config_flags(
        p,
        GuidanceConfig,
        only=GUIDANCE_FIELDS,
        flags={"policy_path": "--policy"},
        defaults={"c_core": True},  # an agent flies one vehicle: the C core's case
    )
    add_config_flags(
        p,
        FailsafeConfig,
        only=(
            "geofence_radius_m",
            *(("require_gcs", "gcs_lost_hold_s", "gcs_lost_land_s") if gcs_failsafe else ()),
        ),
        flags={"require_gcs": "--gcs-failsafe"},
        defaults={"geofence_radius_m": geofence_radius_m},
    )
    add_config_flags(p, ReturnConfig)  # return layers and landing order (agent/returning.py)
    p.add_argument(
        "--no-coordinated-return",
        action="store_true",
        help="return home at its own altitude and land as it arrives (--return-layer-m 0 "
        "--land-radius-m 0); default: on its layer, landing one at a time",
    )
    add_config_flags(
        p,
        ShellConfig,
        only=(
            "idle_state_hz",
            "idle_tick_hz",
            "calm_tick_hz",
            "hold_tick_hz",
            "link_tags",
            "cell_relay",
            "tracking",
            "tracking_lag_s",
        ),
    )
    p.add_argument(
        "--steady-state-hz",
        type=float,
        default=None,
        help=f"state rate in the air while the last state still predicts this vehicle (within "
        f"0.1 m, 0.1 m/s, 0.05 rad; hovering, flying straight), at least "
        f"{MIN_STEADY_STATE_HZ:g}; default: off, always the full rate (comms/state_rate.py)",
    )
    p.add_argument(
        "--hold-state-hz",
        type=float,
        default=SteadyConfig.hold_state_hz,
        help="with --steady-state-hz: the state rate while holding at rest (mode HOLDING, at "
        f"most {HOLD_REST_M_S:g} m/s), at least {1 / MAX_HOLD_PERIOD_S:g} (default "
        f"{SteadyConfig.hold_state_hz:g}); neighbours and the station wait longer for a holder "
        "(comms/state_rate.py)",
    )
    p.add_argument(
        "--one-zenoh-thread",
        action="store_true",
        help="run this process's Zenoh on one worker thread instead of its six (ZENOH_RUNTIME; "
        "a value already in the environment wins): about a tenth less CPU for 40 agents on 2 "
        "cores, measured; off by default (docs/companion.md)",
    )
    p.add_argument(
        "--zenoh-default-pools",
        action="store_true",
        help="keep Zenoh's own thread pools; by default an agent's receive pool hands its work "
        "to the application thread (one wake-up per state heard instead of two; "
        "ZENOH_RUNTIME, a value already in the environment wins; docs/companion.md)",
    )
    p.add_argument("--duration-s", type=float, default=None, help="exit after this long (tests)")
    p.add_argument("-v", "--verbose", action="store_true", help="log at INFO level")


def add_host_args(p: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    """The flags of several simulated vehicles (`covey agent --ids`, `covey fleet-sim`)."""
    add_config_flags(p, ShellConfig, only=("spacing_m", "see_others"))
    add_config_flags(p, GuidanceConfig, only=("max_neighbours",), defaults={"max_neighbours": 10})


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="covey agent",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    who = p.add_mutually_exclusive_group(required=True)
    who.add_argument("--id", type=int, help="vehicle id, 1..65000 (the same as --ids ID)")
    who.add_argument(
        "--ids",
        type=vehicle_ids,
        metavar="IDS",
        help="host these simulated vehicles in one process: ids and ranges, e.g. 1-100 or "
        "1-50,60,70-79",
    )
    add_config_flags(p, ShellConfig, only=("vehicle",))
    add_config_flags(p, ShellConfig, only=("assumed_pos_sigma_m",))
    add_flight_args(p)
    add_config_flags(p, ShellConfig, only=("link", "tick_hz", "state_hz", "trace_guidance"))
    p.add_argument(
        "--plan",
        default=None,
        metavar="FILE",
        help="a signed fleet plan to hold from start (covey plan load writes plan.bin): fence "
        "and keep-out zones apply before any station is reachable; a newer one on the mesh "
        "replaces it",
    )
    add_host_args(p.add_argument_group("multi-vehicle host (--ids only)"))
    # --key-file: this vehicle's (covey keygen add vehicle N); --key-dir: vehicle-<id>.key each
    add_mesh_args(p, key_dir=True)
    return p


def fleet_sim_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="covey fleet-sim",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--vehicles", type=int, default=500, help="vehicles in this process (default 500)"
    )
    p.add_argument("--first-id", type=int, default=1, help="id of the first vehicle (default 1)")
    p.add_argument("--rate-hz", type=float, default=10.0, help="tick and state rate (default 10)")
    add_flight_args(p, geofence_radius_m=2000.0, gcs_failsafe=False)
    add_host_args(p)
    add_mesh_args(p, key_file=False)
    refuse(p, "--key-file", NO_KEY_REASON, show=True)
    refuse(p, "--key-dir", NO_KEY_REASON)
    return p


# -- flags to config ---------------------------------------------------------------------------------
def sim_config(vehicle_model: str, **kw: object) -> SimConfig:
    """The simulator's config for --vehicle-model: ideal = the simulator as it always was (it
    flies the setpoint with SimConfig's acceleration limit and knows where it is), realistic =
    policy.pointmass.VehicleModel.realistic() (0.3 s lag, 2.5 m/s^2, gusts, 0.5 m GNSS drift)."""
    from policy.pointmass import VehicleModel

    model: VehicleModel | None = VehicleModel.named(vehicle_model)
    if model == VehicleModel.ideal():
        model = None
    return SimConfig(vehicle=model, **kw)  # type: ignore[arg-type]


def guidance_from_args(args: argparse.Namespace) -> GuidanceConfig:
    """The guidance the flags ask for (with several vehicles: each call's nearest
    --max-neighbours)."""
    extra = {"max_neighbours": args.max_neighbours} if _hosting(args) else {}
    return config_from_flags(GuidanceConfig, args, only=GUIDANCE_FIELDS, **extra)


def _hosting(args: argparse.Namespace) -> bool:
    """Several simulated vehicles (--ids, fleet-sim), not a single agent (--id)."""
    return getattr(args, "id", None) is None


def steady_from_args(args: argparse.Namespace) -> SteadyConfig | None:
    """The steady-rate rule from --steady-state-hz and --hold-state-hz (None: off); a bad rate
    raises ValueError."""
    hz = args.steady_state_hz
    if hz is None:
        return None
    return SteadyConfig(
        state_hz=hz, hold_state_hz=getattr(args, "hold_state_hz", SteadyConfig.hold_state_hz)
    )


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
    if not hasattr(args, "require_gcs"):
        return FailsafeConfig(
            require_gcs=False, geofence_radius_m=args.geofence_radius_m, returning=returning
        )
    only = ("require_gcs", "gcs_lost_hold_s", "gcs_lost_land_s", "geofence_radius_m")
    return config_from_flags(FailsafeConfig, args, only=only, returning=returning)


def signed_plan(path: str | None) -> FleetPlan | None:
    """The signed fleet plan in `path` (comms/plan_io.py; shapely is imported only then), or
    None; BadPlanError (a ValueError, one line) if it cannot be used."""
    if path is None:
        return None
    from comms.plan_io import read_signed_plan

    return read_signed_plan(path)


def config_from_args(
    args: argparse.Namespace,
    p: argparse.ArgumentParser | None = None,
    ids: tuple[int, ...] | None = None,
) -> ShellConfig:
    """The shell's config from `covey agent`'s flags (or fleet-sim's, given its `ids`); a bad
    value raises ValueError (or, given the parser, exits 2)."""
    if ids is None:
        ids = args.ids if args.ids is not None else (args.id,)
    rate_hz = getattr(args, "rate_hz", None) or args.tick_hz
    one = not _hosting(args)
    return ShellConfig(
        ids=ids,
        # no shared memory: no watchdog thread in every agent (comms/session.py shared_memory)
        mesh=dataclasses.replace(mesh_config(args, p), shared_memory=False),
        vehicle=getattr(args, "vehicle", "sim"),
        tick_hz=rate_hz,
        state_hz=args.state_hz if one else rate_hz,
        idle_state_hz=args.idle_state_hz,
        idle_tick_hz=args.idle_tick_hz,
        steady=steady_from_args(args),
        origin=args.origin or GeoOrigin(),
        guidance=guidance_from_args(args),
        failsafe=failsafe_from_args(args),
        see_others=getattr(args, "see_others", True),
        link=args.link if one else "perfect",
        trace_guidance=args.trace_guidance if one else False,
        plan=signed_plan(args.plan) if one else None,
        sim=sim_config(args.vehicle_model),
        start_ne_m=args.start_ne_m,
        spacing_m=args.spacing_m,
        **given_fields(
            args,
            "assumed_pos_sigma_m",
            "link_tags",
            "cell_relay",
            "calm_tick_hz",
            "hold_tick_hz",
            "tracking",
            "tracking_lag_s",
        ),
    )


def given_fields(args: argparse.Namespace, *names: str) -> dict:
    """The fields among `names` that this command's parser has (fleet-sim has fewer flags)."""
    return {n: getattr(args, n) for n in names if hasattr(args, n)}


def host_config(
    p: argparse.ArgumentParser, args: argparse.Namespace, ids: tuple[int, ...], rate_hz: float
) -> ShellConfig:
    """Several vehicles' config from the shared flags; a bad value exits 2 with the reason."""
    try:
        cfg = dataclasses.replace(config_from_args(args, p, ids), tick_hz=rate_hz, state_hz=rate_hz)
        cfg.mesh.zenoh_config()  # a bad --zenoh-config is refused before anything starts
    except ValueError as exc:
        die(p, str(exc))
    return cfg


# -- running ---------------------------------------------------------------------------------------
def make_backend(cfg: ShellConfig, clock_s: Callable[[], float]) -> VehicleBackend:
    """The one real autopilot `cfg.vehicle` names: mavsdk:<url> | relay:<url>."""
    kind, _, url = cfg.vehicle.partition(":")
    if kind == "mavsdk":
        from agent.backends.mavsdk_backend import MavsdkBackend

        return MavsdkBackend(url or "udpin://0.0.0.0:14540", origin=cfg.origin)
    if kind == "relay":
        from agent.backends.relay import RelayBackend

        return RelayBackend(url or "udpin:0.0.0.0:14550", origin=cfg.origin)
    raise ValueError(f"unknown vehicle {cfg.vehicle!r}: use sim, mavsdk:<url> or relay:<url>")


def make_link(
    spec: str,
    vehicle_id: int,
    receiver_pos: Callable[[], tuple[float, float, float] | None] | None = None,
) -> LinkEmulator | None:
    """The emulated radio between one vehicle and its neighbours, or None for a perfect link."""
    if spec in ("", "perfect"):
        return None
    from comms import link

    return link.emulator_from_spec(
        spec, seed=vehicle_id, receiver_pos=receiver_pos, own_id=vehicle_id
    )


def main(
    cfg: ShellConfig,
    *,
    auths: Mapping[int, FleetAuth] | None = None,
    stop: threading.Event | None = None,
    duration_s: float | None = None,
    ready: Callable[[VehicleShell], None] | None = None,
) -> dict[str, float]:
    """Run the shell of `cfg`'s vehicles until `stop` (or `duration_s`); returns the tick
    statistics. `auths`: one FleetAuth per vehicle (keyed mode), the first of which keys the
    mesh."""
    stop = stop or threading.Event()
    clock_s = time.monotonic
    vid = cfg.ids[0]
    # The duration bounds the whole run, waiting for a router included.
    with contextlib.ExitStack() as stack, stop_after(duration_s, stop):
        backend = None
        if cfg.vehicle.partition(":")[0] != "sim":  # the autopilot link first: it is slow
            backend = stack.enter_context(make_backend(cfg, clock_s))
        mesh = stack.enter_context(Mesh(cfg.mesh, auth=auths[vid] if auths else None, stop=stop))
        own_pos: list[tuple[float, float, float] | None] = [None]  # range-dependent loss
        link = make_link(cfg.link, vid, receiver_pos=lambda: own_pos[0])
        if link is not None:
            link = stack.enter_context(link)
        shell: VehicleShell
        if backend is None:
            shell = stack.enter_context(Fleet(cfg, mesh, auths=auths, clock_s=clock_s, link=link))
        else:
            shell = stack.enter_context(Agent(cfg, backend, mesh, clock_s=clock_s, link=link))
        shell.on_position = lambda pos: own_pos.__setitem__(0, (pos[0, 0], pos[0, 1], pos[0, 2]))
        log.info(
            "vehicles %s up: fleet %s, %s, link %s",
            id_ranges(cfg.ids),
            cfg.mesh.fleet,
            cfg.vehicle,
            cfg.link,
        )
        if ready is not None:
            ready(shell)
        shell.run(stop)
        return shell.stats.summary()


def run(
    p: argparse.ArgumentParser,
    cfg: ShellConfig,
    duration_s: float | None,
    auths: Mapping[int, FleetAuth] | None = None,
) -> int:
    """Run the shell until a signal or `duration_s`: READY once every vehicle answers commands
    and is present, STATS (tick statistics, JSON) at the end."""

    def ready(_shell: VehicleShell) -> None:
        mode = "keyed, one key each" if auths else "OPEN MODE"
        print(f"READY {cfg.vehicles} vehicles {id_ranges(cfg.ids)} ({mode})", flush=True)

    with stop_on_signals() as stop, contextlib.suppress(KeyboardInterrupt):
        try:
            stats = main(cfg, auths=auths, stop=stop, duration_s=duration_s, ready=ready)
        except (ValueError, FileNotFoundError) as exc:  # MeshConfigError: bad config, busy port
            die(p, str(exc))
        print("STATS " + json.dumps(stats), flush=True)
    return 0


def check_duration(p: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    if args.duration_s is not None and not (math.isfinite(args.duration_s) and args.duration_s > 0):
        p.error(f"--duration-s must be a positive number of seconds, got {args.duration_s}")


def cli(argv: list[str]) -> int:
    """`covey agent`."""
    p = parser()
    args = p.parse_args(argv)
    if args.one_zenoh_thread and args.zenoh_default_pools:
        p.error("--one-zenoh-thread and --zenoh-default-pools ask for different pools: pick one")
    if not args.zenoh_default_pools:  # before anything opens Zenoh (comms/session.py)
        use_zenoh_runtime(ONE_THREAD_RUNTIME if args.one_zenoh_thread else AGENT_RUNTIME)
    setup_logging(args.verbose)
    check_duration(p, args)
    kind = args.vehicle.partition(":")[0]
    if args.ids is not None:
        if kind != "sim":
            p.error(
                f"--vehicle {args.vehicle}: --ids hosts simulated vehicles only; a real "
                "autopilot is one per process (covey agent --id N --vehicle ...)"
            )
        for dest, why in SINGLE_FLAGS.items():
            if flags := given(p, args, dest):
                p.error(f"{flags[0]} is refused with --ids: {why}")
    else:
        if flags := given(p, args, *HOST_FLAGS):
            p.error(f"{', '.join(flags)}: a multi-vehicle host's (--ids), not a single agent's")
        if kind != "sim" and given(p, args, "start_ne_m"):
            p.error(f"--start-ne-m places a simulated vehicle; a {kind} vehicle is where it is")
        if kind != "sim" and given(p, args, "vehicle_model"):
            p.error(
                f"--vehicle-model is how a simulated vehicle flies; a {kind} vehicle flies itself"
            )
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
    auths = load_keys(p, args, cfg.ids, cfg.mesh.fleet)
    cfg = dataclasses.replace(cfg, open_mode=auths is None)
    return run(p, cfg, args.duration_s, auths)


def fleet_sim_cli(argv: list[str]) -> int:
    """`covey fleet-sim`: `covey agent --ids` in open mode, ids from --vehicles, --first-id."""
    p = fleet_sim_parser()
    args = p.parse_args(argv)
    setup_logging(args.verbose)
    check_duration(p, args)
    key_env_note(p, NO_KEY_REASON)
    from agent.shell_config import FleetSimConfig

    try:
        ids = FleetSimConfig(vehicles=args.vehicles, first_id=args.first_id).ids
    except ValueError as exc:
        die(p, str(exc))
    return run(p, host_config(p, args, ids, args.rate_hz), args.duration_s)


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
