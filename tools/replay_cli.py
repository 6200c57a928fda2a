"""`covey replay`: play a recording into a fleet, or replay one vehicle's recorded traffic
through a policy and compare its commands (closed loop, tools/closed_loop.py).

    covey replay flight.mcap --fleet demo-replay --speed 2 --loop
    covey replay flight.mcap --policy policy/weights/policy.npz --vehicle 3 [--json-out out.json]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from comms.record import read_recording
from comms.replay import LiveFleetError, ReplayConfig, replay
from groundstation.argtypes import finite, stop_on_signals
from groundstation.meshargs import add_mesh_args, mesh_config


def replay_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="covey replay",
        description="Play a recording into a fleet (states flagged REPLAY; commands are never sent), "
        "or with --policy, replay one vehicle's traffic through a policy and compare its commands.",
    )
    p.add_argument("file", help="MCAP recording")
    p.add_argument(
        "--speed",
        type=finite("times real time", allow_inf=True),
        default=1.0,
        help="playback speed (default 1; inf = as fast as possible)",
    )
    p.add_argument("--loop", action="store_true", help="start over at the end")
    p.add_argument(
        "--start",
        type=finite("seconds", inclusive=True),
        default=0.0,
        metavar="S",
        help="start S seconds into the recording",
    )
    p.add_argument(
        "--end",
        type=finite("seconds", inclusive=True),
        default=None,
        metavar="S",
        help="stop S seconds into the recording",
    )
    p.add_argument(
        "--presence-wait",
        type=finite("seconds", inclusive=True),
        default=1.0,
        metavar="S",
        help="listen this long for live vehicles before replaying (default 1)",
    )
    cl = p.add_argument_group("closed loop")
    cl.add_argument(
        "--policy", default=None, metavar="PATH", help="weights (.npz) to replay through"
    )
    cl.add_argument(
        "--vehicle",
        type=int,
        default=None,
        metavar="ID",
        help="the vehicle whose traffic is replayed",
    )
    cl.add_argument(
        "--json-out", default=None, metavar="PATH", help="also write the closed-loop report as JSON"
    )
    cl.add_argument("--separation-m", type=finite("metres"), default=3.0)
    cl.add_argument("--cruise-speed-m-s", type=finite("m/s"), default=1.0)
    cl.add_argument("--no-safety-filter", action="store_true")
    add_mesh_args(p, key_file=False)  # a recording cannot be re-signed: open-mode fleets only
    p.set_defaults(fleet=None)  # default: the recorded fleet
    for action in p._actions:  # meshargs documents its own default; replay's differs
        if action.dest == "fleet":
            action.help = "fleet to replay into (default: the recorded fleet)"
    return p


def replay_cli(argv: list[str]) -> int:
    p = replay_parser()
    args = p.parse_args(argv)
    if not Path(args.file).is_file():
        p.error(f"no recording at {args.file}")
    if args.policy is not None or args.vehicle is not None:
        if args.policy is None or args.vehicle is None:
            p.error("closed-loop replay needs both --policy PATH and --vehicle ID")
        return _closed_loop_cli(args, p)
    rec = read_recording(args.file)
    if rec.truncated:
        print(
            f"note: {args.file} was cut off ({rec.truncated}); replaying what is there",
            file=sys.stderr,
        )
    if args.fleet is None:
        args.fleet = rec.fleet or "covey"
    try:
        cfg = ReplayConfig(
            path=args.file,
            mesh=mesh_config(args, p),
            speed=args.speed,
            loop=args.loop,
            start_s=args.start,
            end_s=args.end,
            presence_wait_s=args.presence_wait,
        )
    except ValueError as exc:
        p.error(str(exc))
    stop = stop_on_signals()
    print(f"replaying {args.file} into fleet {cfg.mesh.fleet!r} at {cfg.speed:g}x", file=sys.stderr)
    try:
        result = replay(cfg, stop, recording=rec)
    except LiveFleetError as exc:
        print(f"covey replay: refused: {exc}", file=sys.stderr)
        return 1
    except ValueError as exc:
        print(f"covey replay: {exc}", file=sys.stderr)
        return 2
    print(
        f"replayed {result.states} states and {result.events} events in {result.loops} pass(es); "
        f"{result.commands_skipped} recorded commands not sent"
    )
    return 0


def _closed_loop_cli(args: argparse.Namespace, p: argparse.ArgumentParser) -> int:
    from tools.closed_loop import ClosedLoopConfig, format_report, run_closed_loop

    try:
        cfg = ClosedLoopConfig(
            path=args.file,
            vehicle_id=args.vehicle,
            policy_path=args.policy,
            separation_m=args.separation_m,
            cruise_speed_m_s=args.cruise_speed_m_s,
            safety_filter=not args.no_safety_filter,
            start_s=args.start,
            end_s=args.end,
        )
        report = run_closed_loop(cfg)
    except (ValueError, FileNotFoundError) as exc:
        print(f"covey replay: {exc}", file=sys.stderr)
        return 2
    print(format_report(report))
    text = json.dumps(report, indent=2)
    if args.json_out:
        Path(args.json_out).write_text(text + "\n")
    print(text)
    return 0
