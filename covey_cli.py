"""`covey`: one command, many subcommands. Each subcommand lives in its own module and is imported
only when used, so `covey --help` is fast and the runtime never imports torch.

A subcommand's module has `<x>cli(argv)`, which parses and runs, and `<x>parser()`, which builds
its argparse parser (`cli`/`parser`, `record_cli`/`record_parser`, ...): tests check every
subcommand's options through `parser_of`. Shared options: cli/options.py.
"""

from __future__ import annotations

import argparse
import importlib
import sys

# name: (module, function taking argv, one-line help)
SUBCOMMANDS: dict[str, tuple[str, str, str]] = {
    "demo": (
        "groundstation.demo",
        "cli",
        "simulated fleet + browser ground station, no external services",
    ),
    "agent": (
        "agent.agent_cli",
        "cli",
        "run the agent of one vehicle (sim, MAVSDK or MAVLink relay), or of many (--ids)",
    ),
    "gcs": ("groundstation.gcs_cli", "cli", "browser ground station (viser)"),
    "router": (
        "tools.router_cli",
        "cli",
        "the Zenoh router of one site of a multi-site fleet",
    ),
    "status": (
        "groundstation.ops",
        "status_cli",
        "print the fleet: presence, last state, link age",
    ),
    "cmd": ("groundstation.ops", "cmd_cli", "send one command and print every vehicle's ack"),
    "mission": (
        "groundstation.mission_cli",
        "mission_cli",
        "upload a mission (covey JSON or QGC .plan), start/pause/resume/abort it, show progress",
    ),
    "train": ("policy.train_cli", "cli", "train the guidance policy with PPO (needs covey[train])"),
    "eval": (
        "agent.eval_agents",
        "eval_cli",
        "evaluate policies against ORCA and straight-line baselines",
    ),
    "export": (
        "firmware.export_c",
        "export_cli",
        "export a checkpoint to runtime weights (--format npz|c)",
    ),
    "sitl": ("firmware.sitl.sitl_cli", "cli", "PX4-compatible MAVLink autopilot emulator"),
    "record": (
        "tools.record_cli",
        "record_cli",
        "record the mesh to MCAP (--info FILE summarises)",
    ),
    "foxglove": (
        "recording.foxglove_bridge",
        "cli",
        "serve the live fleet to Foxglove (WebSocket), same channels as a recording",
    ),
    "replay": (
        "tools.replay_cli",
        "replay_cli",
        "replay an MCAP recording into a fleet",
    ),
    "keygen": (
        "groundstation.keygen_cli",
        "keygen_cli",
        "fleet authority: init, add/revoke members, push the roster",
    ),
    "plan": (
        "groundstation.plan_cli",
        "plan_cli",
        "fleet plan: load a GeoJSON/QGC fence and keep-out zones, show, push to the fleet",
    ),
    "tls": (
        "groundstation.tls_cli",
        "tls_cli",
        "fleet TLS: a CA, one certificate per identity, ready-to-use Zenoh configs",
    ),
    "fleet-sim": (
        "agent.agent_cli",
        "fleet_sim_cli",
        "simulate hundreds of vehicles in one process (open mode; covey agent --ids keyed)",
    ),
    "intruder": (
        "tools.intruder_cli",
        "cli",
        "fly one simulated non-cooperative vehicle through the fleet (traffic)",
    ),
    "bench": ("bench.__main__", "cli", "run the benchmark suite"),
}


def parser_of(name: str) -> argparse.ArgumentParser:
    """The argparse parser of subcommand `name` (its module's `<x>parser()`)."""
    module_name, func_name, _ = SUBCOMMANDS[name]
    builder = func_name.removesuffix("cli") + "parser"
    return getattr(importlib.import_module(module_name), builder)()


def usage() -> str:
    width = max(map(len, SUBCOMMANDS))
    lines = [
        "usage: covey <command> [options]   (covey <command> --help for its options)",
        "",
        "commands:",
    ]
    lines += [f"  {name:<{width}}  {text}" for name, (_, _, text) in SUBCOMMANDS.items()]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(usage())
        return 0
    name, rest = argv[0], argv[1:]
    if name not in SUBCOMMANDS:
        print(f"covey: unknown command {name!r}\n\n{usage()}", file=sys.stderr)
        return 2
    module_name, func_name, _ = SUBCOMMANDS[name]
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        print(f"covey {name}: not available in this install ({exc}).", file=sys.stderr)
        if exc.name == "torch":
            print("Install the training extra: pip install -e '.[train]'", file=sys.stderr)
        return 2
    result = getattr(module, func_name)(rest)
    # An int is an exit status; a subcommand may also return its results (train, eval): success.
    return result if isinstance(result, int) and not isinstance(result, bool) else 0


if __name__ == "__main__":
    sys.exit(main())
