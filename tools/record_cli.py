"""`covey record`: record a fleet's mesh to MCAP, summarise a recording, or add Foxglove's
channels to one.

    covey record -o flight.mcap --fleet demo --connect tcp/127.0.0.1:7447 --duration-s 60
    covey record --info flight.mcap [--json]
    covey record --foxglove-from old.mcap -o new.mcap     (add Foxglove's channels to a recording)
"""

from __future__ import annotations

import argparse
import json
import sys

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
from recording.foxglove_bridge import add_foxglove_args, foxglove_config
from recording.record import (
    PARTIAL_EXIT,
    FoxgloveIncomplete,
    RecordConfig,
    add_foxglove_channels,
    format_info,
    partial_warning,
    read_recording,
    record,
    summarise,
)

RECORD_NO_KEY = (
    "a recorder stores the mesh's bytes as they are, signatures included, and signs nothing "
    "(covey record needs no key to record a keyed fleet)"
)
MESH_DESTS = ("fleet", "connect", "listen", "mesh_mode", "zenoh_config")


def record_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="covey record", description="Record every message of a fleet's mesh to MCAP."
    )
    p.add_argument(
        "-o", "--output", default="flight.mcap", help="MCAP file to write (default flight.mcap)"
    )
    p.add_argument(
        "--duration-s",
        type=finite("seconds"),
        default=None,
        metavar="S",
        help="stop after S seconds",
    )
    renamed(p, {"--duration": "--duration-s"})
    p.add_argument(
        "--info", metavar="FILE", default=None, help="summarise a recording instead of recording"
    )
    p.add_argument("--json", action="store_true", help="with --info: print JSON")
    p.add_argument(
        "--foxglove-from",
        metavar="OLD",
        default=None,
        help="instead of recording: copy recording OLD to -o with Foxglove's standard "
        "channels added (its covey channels stay byte for byte)",
    )
    p.add_argument(
        "--no-foxglove",
        action="store_true",
        help="record covey's channels only, without Foxglove's standard ones",
    )
    add_foxglove_args(p)
    add_mesh_args(
        p,
        key_file=False,
        mode_default="client",
        mode_help="default: client, of the router at --connect, which hands it every message "
        "from a vehicle's first one on; as a peer it hears a vehicle that just started only "
        "once their gossip link is up, and can miss its first states",
    )
    refuse(p, "--key-file", RECORD_NO_KEY, show=True)
    return p


def foxglove_from_main(src: str, dst: str, args: argparse.Namespace) -> int:
    """Copy `src` with Foxglove's channels added; PARTIAL_EXIT, with a warning that says what
    was kept, when `src` is cut off or corrupted."""
    try:
        rec = read_recording(src)
        if not rec.messages:
            raise ValueError(
                f"{src} holds no covey messages" + (f" ({rec.truncated})" * bool(rec.truncated))
            )
        counts = add_foxglove_channels(src, dst, foxglove_config(args), recording=rec)
    except (FileNotFoundError, ValueError) as exc:
        print(f"covey record: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"covey record: cannot write {dst}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    print(f"wrote {dst}: " + ", ".join(f"{k} {v}" for k, v in sorted(counts.items())))
    if rec.truncated:
        print(partial_warning(rec, src), file=sys.stderr)
        return PARTIAL_EXIT
    return 0


def info_main(path: str, as_json: bool = False, out=sys.stdout) -> int:
    info = summarise(read_recording(path))
    print(json.dumps(info, indent=2) if as_json else format_info(info, path), file=out)
    return 0


def record_cli(argv: list[str]) -> int:
    p = record_parser()
    args = p.parse_args(argv)
    if args.json and not args.info:
        p.error("--json prints the summary of --info FILE; a recording run prints no JSON")
    if args.info or args.foxglove_from:
        mode = "--info" if args.info else "--foxglove-from"
        unused = ["duration_s", *MESH_DESTS] + (
            ["output", "no_foxglove", "origin", "separation_m"] if args.info else []
        )
        if flags := given(p, args, *unused):
            p.error(f"{', '.join(flags)}: not used with {mode}, which reads a recording file")
    elif args.no_foxglove and (flags := given(p, args, "origin", "separation_m")):
        p.error(f"{', '.join(flags)}: draws Foxglove's channels, which --no-foxglove leaves out")
    if args.info:
        try:
            return info_main(args.info, args.json)
        except (FileNotFoundError, ValueError) as exc:  # ValueError: not an MCAP file
            die(p, str(exc))
    if args.foxglove_from:
        if args.no_foxglove:
            p.error("--foxglove-from adds the Foxglove channels; it cannot take --no-foxglove")
        return foxglove_from_main(args.foxglove_from, args.output, args)
    try:
        cfg = RecordConfig(
            path=args.output,
            mesh=mesh_config(args, p),
            duration_s=args.duration_s,
            foxglove=None if args.no_foxglove else foxglove_config(args),
        )
    except ValueError as exc:
        p.error(str(exc))
    try:
        cfg.mesh.zenoh_config()  # a bad --zenoh-config is refused before anything starts
    except ValueError as exc:
        die(p, str(exc))
    key_env_note(p, RECORD_NO_KEY)
    print(f"recording fleet {cfg.mesh.fleet!r} to {cfg.path} (Ctrl-C to stop)", file=sys.stderr)
    try:
        with stop_on_signals() as stop:
            counts = record(cfg, stop)
    except MeshUnreachable as exc:  # no router answered within --duration-s or before Ctrl-C
        return nobody_answered(p, exc)
    except FoxgloveIncomplete as exc:  # covey's channels are whole; Foxglove's can be added later
        print(f"covey record: {' '.join(str(exc).split())}", file=sys.stderr)
        return 1
    except OSError as exc:
        print(f"covey record: cannot write {cfg.path}: {exc}", file=sys.stderr)
        return 2
    except ValueError as exc:  # MeshConfigError: bad --zenoh-config, endpoint, busy port
        die(p, str(exc))
    total = sum(counts.values())
    print(
        f"wrote {total} messages to {cfg.path}: "
        + ", ".join(f"{k} {v}" for k, v in sorted(counts.items()))
    )
    return 0
