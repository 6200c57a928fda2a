"""`covey replay`: play a recording into a fleet, or replay one vehicle's recorded traffic
through a policy and compare its commands (closed loop, tools/closed_loop.py).

    covey replay flight.mcap --fleet demo-replay --speed 2 --loop --start-s 10
    covey replay flight.mcap --policy policy/weights/policy.npz --vehicle 3 [--json-out out.json]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from cli.options import (
    add_mesh_args,
    die,
    finite,
    given,
    key_env_note,
    mesh_config,
    nobody_answered,
    refuse,
    renamed,
    stop_on_signals,
)
from comms.session import MeshUnreachable
from recording.record import PARTIAL_EXIT, partial_warning, read_recording
from recording.replay import LiveFleetError, ReplayConfig, replay

REPLAY_NO_KEY = (
    "a replay cannot be signed: replayed states carry the REPLAY flag, which their vehicles' "
    "signatures do not cover, and one member key cannot sign for every recorded vehicle; "
    "replay into an open-mode fleet (--fleet NAME)"
)
MESH_DESTS = ("fleet", "connect", "listen", "mesh_mode", "zenoh_config")


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
        "--start-s",
        type=finite("seconds", inclusive=True),
        default=0.0,
        metavar="S",
        help="start S seconds into the recording",
    )
    p.add_argument(
        "--end-s",
        type=finite("seconds", inclusive=True),
        default=None,
        metavar="S",
        help="stop S seconds into the recording",
    )
    p.add_argument(
        "--presence-wait-s",
        type=finite("seconds", inclusive=True),
        default=1.0,
        metavar="S",
        help="listen this long for live vehicles before replaying (default 1)",
    )
    renamed(
        p,
        {
            "--start": "--start-s",
            "--end": "--end-s",
            "--presence-wait": "--presence-wait-s",
        },
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
    cl.add_argument(
        "--separation-m",
        type=finite("metres"),
        default=3.0,
        help="separation the policy keeps (default 3)",
    )
    cl.add_argument(
        "--cruise-speed-m-s",
        type=finite("m/s"),
        default=1.0,
        help="cruise speed of the policy (default 1)",
    )
    cl.add_argument("--no-safety-filter", action="store_true", help="replay the pure policy")
    add_mesh_args(
        p,
        key_file=False,
        fleet_default=None,
        fleet_help="fleet to replay into (default: the recorded fleet)",
    )
    refuse(p, "--key-file", REPLAY_NO_KEY, show=True)
    return p


CLOSED_LOOP_ONLY = ("json_out", "separation_m", "cruise_speed_m_s", "no_safety_filter")
INTO_FLEET_ONLY = ("speed", "loop", "presence_wait_s", *MESH_DESTS)


def replay_cli(argv: list[str]) -> int:
    p = replay_parser()
    args = p.parse_args(argv)
    if not Path(args.file).is_file():
        p.error(f"no recording at {args.file}")
    if args.policy is not None or args.vehicle is not None:
        if args.policy is None or args.vehicle is None:
            p.error("closed-loop replay needs both --policy PATH and --vehicle ID")
        if flags := given(p, args, *INTO_FLEET_ONLY):
            p.error(f"{', '.join(flags)}: closed-loop replay (--policy) publishes nothing")
        return _closed_loop_cli(args, p)
    if flags := given(p, args, *CLOSED_LOOP_ONLY):
        p.error(f"{', '.join(flags)}: closed-loop replay only (with --policy and --vehicle)")
    try:
        rec = read_recording(args.file)
    except (FileNotFoundError, ValueError) as exc:  # not an MCAP file
        die(p, str(exc))
    if not rec.messages:
        die(
            p,
            f"{args.file} holds no covey messages" + (f" ({rec.truncated})" * bool(rec.truncated)),
        )
    if rec.truncated:  # replay what is there, say how much, and exit PARTIAL_EXIT
        print(partial_warning(rec, args.file), file=sys.stderr)
    if args.fleet is None:
        args.fleet = rec.fleet or "covey"
    try:
        cfg = ReplayConfig(
            path=args.file,
            mesh=mesh_config(args, p),
            speed=args.speed,
            loop=args.loop,
            start_s=args.start_s,
            end_s=args.end_s,
            presence_wait_s=args.presence_wait_s,
        )
    except ValueError as exc:
        p.error(str(exc))
    try:
        cfg.mesh.zenoh_config()  # a bad --zenoh-config is refused before anything starts
    except ValueError as exc:
        die(p, str(exc))
    key_env_note(p, REPLAY_NO_KEY)
    print(f"replaying {args.file} into fleet {cfg.mesh.fleet!r} at {cfg.speed:g}x", file=sys.stderr)
    try:
        with stop_on_signals() as stop:
            result = replay(cfg, stop, recording=rec)
    except LiveFleetError as exc:
        print(f"covey replay: refused: {exc}", file=sys.stderr)
        return 1
    except MeshUnreachable as exc:  # replaying into nothing: said, nothing sent, exit 1
        return nobody_answered(p, exc)
    except ValueError as exc:  # MeshConfigError (a busy port), an empty window
        die(p, str(exc))
    print(
        f"replayed {result.states} states and {result.events} events in {result.loops} pass(es); "
        f"{result.commands_skipped} recorded commands not sent"
    )
    return PARTIAL_EXIT if rec.truncated else 0


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
            start_s=args.start_s,
            end_s=args.end_s,
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
