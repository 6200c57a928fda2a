"""The command lines of the multi-vehicle host: `covey agent --ids` and `covey fleet-sim`.

    covey agent --ids 1-100 --key-dir keys/ --connect tcp/10.0.0.1:7447
    covey fleet-sim --vehicles 500 --connect tcp/127.0.0.1:7447 --rate-hz 10

Both run agent/fleet_sim.py's `Fleet` (the flight core with one row per vehicle around the
vectorised simulator) with the flags `covey agent` shares with it (agent/agent_cli.py).
`covey agent --ids` is the fleet member: keyed with one key per vehicle (--key-dir), the
ground-station failsafe on by default, as a single agent. `covey fleet-sim` is its open-mode
alias for scale tests and benches: ids from --vehicles and --first-id, no ground-station
failsafe, a 2 km geofence, nothing signed.
"""

from __future__ import annotations

import argparse
import contextlib
import json
from collections.abc import Mapping

from agent import agent_cli
from agent.fleet_sim import Fleet, FleetSimConfig
from cli.options import (
    add_mesh_args,
    die,
    given,
    id_ranges,
    key_env_note,
    mesh_config,
    refuse,
    setup_logging,
    stop_on_signals,
)
from comms.geo import GeoOrigin
from trust.auth import FleetAuth


def host_config(
    p: argparse.ArgumentParser, args: argparse.Namespace, ids: tuple[int, ...], rate_hz: float
) -> FleetSimConfig:
    """The host's config from the shared flags; a bad value exits 2 with the reason."""
    try:
        cfg = FleetSimConfig(
            ids=ids,
            mesh=mesh_config(args, p),
            rate_hz=rate_hz,
            idle_state_hz=args.idle_state_hz,
            steady=agent_cli.steady_from_args(args),
            spacing_m=args.spacing_m,
            start_ne_m=args.start_ne_m,
            max_neighbours=args.max_neighbours,
            see_others=not args.no_see_others,
            guidance=agent_cli.guidance_from_args(args),
            failsafe=agent_cli.failsafe_from_args(args),
            origin=args.origin or GeoOrigin(),
            sim=agent_cli.sim_config(args.vehicle_model),
        )
        cfg.mesh.zenoh_config()  # a bad --zenoh-config is refused before anything starts
    except ValueError as exc:
        die(p, str(exc))
    return cfg


def run(
    p: argparse.ArgumentParser,
    cfg: FleetSimConfig,
    duration_s: float | None,
    auths: Mapping[int, FleetAuth] | None = None,
) -> int:
    """Run the host until a signal or `duration_s`: READY once every vehicle answers commands
    and is present, STATS (tick statistics, JSON) at the end."""
    from agent.fleet_sim import main

    def ready(_fleet: Fleet) -> None:
        mode = "keyed, one key each" if auths else "OPEN MODE"
        print(f"READY {cfg.vehicles} vehicles {id_ranges(cfg.ids)} ({mode})", flush=True)

    with stop_on_signals() as stop, contextlib.suppress(KeyboardInterrupt):
        try:
            stats = main(cfg, stop=stop, duration_s=duration_s, ready=ready, auths=auths)
        except (ValueError, FileNotFoundError) as exc:  # MeshConfigError: bad config, busy port
            die(p, str(exc))
        print("STATS " + json.dumps(stats), flush=True)
    return 0


# -- covey agent --ids -------------------------------------------------------------------------------
def run_agent_host(p: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    """`covey agent --ids ...` (parsed by agent_cli.parser)."""
    kind = args.vehicle.partition(":")[0]
    if kind != "sim":
        p.error(
            f"--vehicle {args.vehicle}: --ids hosts simulated vehicles only; a real autopilot "
            "is one per process (covey agent --id N --vehicle ...)"
        )
    for dest, why in agent_cli.SINGLE_FLAGS.items():
        if flags := given(p, args, dest):
            p.error(f"{flags[0]} is refused with --ids: {why}")
    cfg = host_config(p, args, args.ids, args.tick_hz)
    auths = agent_cli.load_keys(p, args, cfg.ids, cfg.mesh.fleet)
    return run(p, cfg, args.duration_s, auths)


# -- covey fleet-sim ---------------------------------------------------------------------------------
NO_KEY_REASON = (
    "fleet-sim is the open-mode host for scale tests: to sign, run covey agent --ids "
    "with --key-dir (one key per vehicle)"
)


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
    agent_cli.add_flight_args(p, geofence_radius_m=2000.0, gcs_failsafe=False)
    agent_cli.add_host_args(p)
    add_mesh_args(p, key_file=False)
    refuse(p, "--key-file", NO_KEY_REASON, show=True)
    refuse(p, "--key-dir", NO_KEY_REASON)
    return p


def fleet_sim_cli(argv: list[str]) -> int:
    p = fleet_sim_parser()
    args = p.parse_args(argv)
    setup_logging(args.verbose)
    agent_cli.check_duration(p, args)
    key_env_note(p, NO_KEY_REASON)
    try:
        ids = FleetSimConfig(vehicles=args.vehicles, first_id=args.first_id).ids
    except ValueError as exc:
        die(p, str(exc))
    return run(p, host_config(p, args, ids, args.rate_hz), args.duration_s)
