"""`covey mission`: upload a route to vehicles, start, pause, resume or abort it, ask for it.

    covey mission upload survey.plan --to 1-3 --spread-m 8   # one copy each, 8 m apart east
    covey mission upload route.json --to all                 # covey JSON (groundstation/mission_io.py)
    covey mission start --to 1-3
    covey mission pause --to 2          # hold in place; resume continues the current item
    covey mission resume --to 2
    covey mission abort --to all        # hold; a start flies from item 1 again
    covey mission show --to 1-3         # each vehicle's mission and progress, from the vehicle

Every vehicle answers with a signed ack (accepted, or refused with its reason: an item outside
the fence or in a keep-out zone, an altitude it cannot reach, no mission...). A bad file, a
bad flag, or (keyed) a target that is not a vehicle of the fleet roster is one line and exit 2,
before anything is sent; exit 1 when any addressed vehicle refused or did not answer.
"""

from __future__ import annotations

import argparse
import sys
import threading
from collections.abc import Callable
from dataclasses import dataclass

from cli.options import (
    add_mesh_args,
    die,
    finite,
    mesh_config,
    nobody_answered,
    stop_on_signals,
)
from comms.commands import CommandResult, OutcomeStatus, new_nonce
from comms.mesh import Mesh
from comms.schema import (
    MAX_MISSION_BYTES,
    CommandKind,
    Mission,
    MissionItem,
    Role,
)
from comms.session import MeshConfig, MeshUnreachable, expects_answer, unreachable, wait_linked
from groundstation import dispatch, inputs
from groundstation.inputs import CommandRequest, InputError
from groundstation.mission_io import BadFileError, load_mission_file, shifted
from groundstation.ops import CmdConfig, cmd_main, format_result
from trust.auth import load_auth

CONTROL = {
    "start": CommandKind.MISSION_START,
    "pause": CommandKind.MISSION_PAUSE,
    "resume": CommandKind.MISSION_RESUME,
    "abort": CommandKind.MISSION_ABORT,
    "show": CommandKind.MISSION_STATUS,
}
MAX_SPREAD_M = 1000.0


@dataclass(frozen=True)
class UploadConfig:
    """One mission upload."""

    mesh: MeshConfig
    """How to join the mesh."""
    items: tuple[MissionItem, ...]
    """The mission's items, checked (groundstation/mission_io.py)."""
    targets: tuple[int, ...]
    """Vehicle ids; () = every vehicle present (keyed: of the roster)."""
    mission_id: int = 1
    """The operator's number for the mission (shown in progress and events)."""
    mission_version: int = 1
    spread_m: float = 0.0
    """0: one mission for all targets; else each vehicle its own copy, the k-th (in id order)
    moved k * spread_m metres east."""
    timeout_s: float = 3.0
    """How long to wait for the acks."""
    discover_s: float = 1.0
    """How long to wait for presence to learn who is there."""
    key_file: str | None = None
    """The station's member key file that signs the mission; None: $COVEY_FLEET_KEY_FILE, else
    open mode."""
    source_id: int = 1


class NotInRoster(ValueError):
    """A target is not a vehicle of the fleet roster (keyed mode): nothing was sent."""


def missions_for(cfg: UploadConfig, present: set[int], stamp_ns: int) -> list[Mission]:
    """The Missions to send: one per vehicle with a spread, else one for all the targets (split
    by targets so that each fits MAX_MISSION_BYTES)."""

    def one(items: tuple[MissionItem, ...], targets: tuple[int, ...]) -> Mission:
        return Mission(
            nonce=new_nonce(),
            stamp_ns=stamp_ns,
            items=items,
            mission_id=cfg.mission_id,
            mission_version=cfg.mission_version,
            targets=targets,
            source_id=cfg.source_id,
        )

    if cfg.spread_m:
        ids = sorted(cfg.targets or present)
        return [one(shifted(cfg.items, k * cfg.spread_m), (vid,)) for k, vid in enumerate(ids)]
    if not cfg.targets:
        return [one(cfg.items, ())]
    room = (MAX_MISSION_BYTES - Mission.size(0, len(cfg.items))) // 2
    ts = cfg.targets
    return [one(cfg.items, ts[k : k + room]) for k in range(0, len(ts), room)]


def upload_main(
    cfg: UploadConfig, out: Callable[[str], None] = print, stop: threading.Event | None = None
) -> int:
    """Send the mission and print every vehicle's answer. Raises MeshUnreachable (nobody at
    cfg.mesh.connect) or NotInRoster (keyed: a target outside the roster) before sending."""
    auth = load_auth(cfg.key_file, fleet=cfg.mesh.fleet)
    if auth is not None:
        outside = [v for v in cfg.targets if not auth.is_member(Role.VEHICLE, v)]
        if outside:
            raise NotInRoster(
                f"vehicle {', '.join(map(str, outside))} is not in fleet roster "
                f"v{auth.roster.version}: no mission sent"
            )
    results: list[CommandResult] = []
    with Mesh(cfg.mesh, auth=auth, stop=stop, wait_s=cfg.timeout_s) as mesh:
        if expects_answer(cfg.mesh) and not wait_linked(mesh.session, cfg.timeout_s, stop):
            raise unreachable(cfg.mesh, cfg.timeout_s)
        pres = mesh.presence()
        wanted = set(cfg.targets)
        pres.wait_for(
            (lambda v, _g: wanted <= set(v)) if wanted else (lambda v, _g: False),
            timeout_s=cfg.discover_s,
        )
        present = dispatch.expected_for_all(pres.vehicles, auth)
        for mission in missions_for(cfg, present, mesh.clock_ns()):
            expect = set(mission.targets) if mission.targets else present
            results.append(mesh.send_command(mission, expect=expect, timeout_s=cfg.timeout_s))
    n = len(cfg.items)
    out(f"mission {cfg.mission_id} v{cfg.mission_version} ({n} items):")
    bad = 0
    for res in results:
        out(format_result(res))
        bad += sum(o.status is not OutcomeStatus.ACCEPTED for o in res.outcomes.values())
        bad += not res.outcomes
    return 0 if results and not bad else 1


def mission_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="covey mission",
        description="upload a mission to vehicles, start/pause/resume/abort it, show progress",
    )
    sub = p.add_subparsers(dest="verb", required=True, metavar="VERB")
    texts = {
        "upload": "upload FILE (covey mission JSON or a QGC .plan) to the vehicles",
        "start": "fly the uploaded mission from item 1",
        "pause": "hold in place; the mission waits at its current item",
        "resume": "continue a paused mission's current item",
        "abort": "hold in place and drop the progress (start flies from item 1 again)",
        "show": "ask each vehicle for its mission and progress",
    }
    for verb, text in texts.items():
        sp = sub.add_parser(verb, help=text, description=text)
        if verb == "upload":
            sp.add_argument("file", help="covey mission JSON or QGroundControl .plan file")
            sp.add_argument(
                "--mission-id",
                type=int,
                default=None,
                help="mission number (default: the file's, or 1)",
            )
            sp.add_argument(
                "--spread-m",
                type=finite("metres"),
                default=0.0,
                help="each vehicle its own copy, the k-th moved k * SPREAD_M metres east "
                "(default 0: one mission, the same route for all)",
            )
        sp.add_argument("--to", required=True, help="vehicle ids (1,2,5 or 1-4) or 'all'")
        sp.add_argument(
            "--timeout-s",
            type=finite("seconds"),
            default=3.0,
            help="seconds to wait for acks (default 3)",
        )
        add_mesh_args(sp)
    return p


def mission_cli(argv: list[str] | None = None) -> int:
    p = mission_parser()
    args = p.parse_args(list(sys.argv[1:] if argv is None else argv))
    try:
        targets = inputs.targets(args.to)
    except InputError as exc:
        die(p, f"{args.verb}: " + str(exc).replace("Targets:", "--to", 1))
    if not 0.1 <= args.timeout_s <= 60:
        die(p, f"--timeout-s {args.timeout_s:g} must be within 0.1..60 s")
    mesh = mesh_config(args, p)
    try:
        with stop_on_signals() as stop:
            if args.verb != "upload":
                cfg = CmdConfig(
                    mesh=mesh,
                    request=CommandRequest(CONTROL[args.verb]),
                    targets=targets,
                    timeout_s=args.timeout_s,
                    key_file=args.key_file,
                )
                return cmd_main(cfg, stop=stop)
            if not 0.0 <= args.spread_m <= MAX_SPREAD_M:
                die(p, f"--spread-m {args.spread_m:g} must be within 0..{MAX_SPREAD_M:g} m")
            try:
                loaded = load_mission_file(args.file)
            except BadFileError as exc:
                die(p, str(exc))
            mission_id = loaded.mission_id if args.mission_id is None else args.mission_id
            if not 0 <= mission_id < 2**32:
                die(p, f"--mission-id {mission_id} must be within 0..2^32-1")
            up_cfg = UploadConfig(
                mesh=mesh,
                items=loaded.items,
                targets=targets,
                mission_id=mission_id,
                spread_m=args.spread_m,
                timeout_s=args.timeout_s,
                key_file=args.key_file,
            )
            return upload_main(up_cfg, stop=stop)
    except MeshUnreachable as exc:
        return nobody_answered(p, exc)
    except ValueError as exc:  # NotInRoster, FleetKeyError, MeshConfigError: one line, exit 2
        die(p, str(exc))
