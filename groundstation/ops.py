"""`covey status` and `covey cmd`: the fleet and one command from a terminal.

    covey status --connect tcp/127.0.0.1:7447
    covey cmd takeoff 5 --to all
    covey cmd goto 10 0 5 --to 1,2        # N 10 m, E 0 m, 5 m above the fleet origin
    covey cmd kill --to 3 --yes

`covey cmd` exits non-zero when any addressed vehicle rejected, failed or timed out.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from cli.options import (
    add_mesh_args,
    die,
    finite,
    mesh_config,
    nobody_answered,
    renamed,
    stop_on_signals,
)
from comms.commands import CommandResult, OutcomeStatus
from comms.mesh import Mesh
from comms.schema import CommandKind
from comms.session import (
    MeshConfig,
    MeshUnreachable,
    expects_answer,
    linked,
    unreachable,
    wait_linked,
)
from comms.state_rate import MAX_IDLE_PERIOD_S
from groundstation import dispatch, formation_cmd, inputs
from groundstation.fleet import FleetConfig, FleetModel, FleetSnapshot
from groundstation.inputs import CommandRequest, InputError
from trust.auth import load_auth


@dataclass(frozen=True)
class StatusConfig:
    """What `covey status` does."""

    mesh: MeshConfig = field(default_factory=MeshConfig)
    """How to join the mesh."""
    listen_s: float = 1.5
    """How long to listen for presence and states before printing."""
    key_file: str | None = None
    """A member key file: only states that verify against its roster are shown; None: open mode."""


def format_status(snap: FleetSnapshot) -> str:
    lines = [
        f"{'id':>5} {'alive':>5} {'mode':<10} {'arm':>3} {'N m':>7} {'E m':>7} {'alt m':>6} "
        f"{'m/s':>5} {'bat%':>5} {'Hz':>5} {'age s':>6} {'loss%':>5} {'mission':>7}"
    ]
    for v in snap.vehicles:
        s = v.state
        if s is None:
            lines.append(f"{v.vehicle_id:>5} {'yes' if v.alive else 'no':>5} {'(no state)':<10}")
            continue
        lines.append(
            f"{v.vehicle_id:>5} {'yes' if v.alive else 'LOST':>5} {s.mode.name:<10} {'yes' if s.armed else 'no':>3} "
            f"{s.pos_ned_m[0]:>7.1f} {s.pos_ned_m[1]:>7.1f} {v.alt_m:>6.1f} {v.speed_m_s:>5.1f} "
            f"{s.battery_pct:>5.0f} {f'{v.rate_hz:.1f}' if v.rate_hz else '-':>5} "
            f"{v.age_s:>6.2f} {v.loss_pct:>5.0f} {_progress(s):>7}"
        )
    if snap.close_pairs:
        lines.append(
            "TOO CLOSE: " + ", ".join(f"{a}-{b} {d:.1f} m" for a, b, d in snap.close_pairs)
        )
    return "\n".join(lines)


def _progress(s) -> str:
    """A state's mission progress as `covey status` shows it: item k/n, done, or '-'."""
    k, n = s.mission_item, s.mission_items
    return "-" if not n else "done" if k > n else f"{k}/{n}"


def status_main(
    cfg: StatusConfig, out: Callable[[str], None] = print, stop: threading.Event | None = None
) -> int:
    """Print the fleet. Raises MeshUnreachable when no router or peer answered at
    cfg.mesh.connect within listen_s (a client's wait for its router included)."""
    auth = load_auth(cfg.key_file, fleet=cfg.mesh.fleet)
    fleet = FleetModel(FleetConfig(verified_only=auth is not None))  # keyed: no bare tokens
    with Mesh(cfg.mesh, auth=auth, stop=stop, wait_s=cfg.listen_s) as mesh:
        mesh.subscribe_feed(
            fleet.on_state, on_refused=fleet.on_state_refused
        )  # the whole fleet at a bounded rate, as the station

        def on_presence(kind: str, vid: int, alive: bool) -> None:
            if kind == "vehicle":
                fleet.on_presence(vid, alive, time.time_ns())

        pres = mesh.presence(on_presence)
        (stop or threading.Event()).wait(cfg.listen_s)
        if expects_answer(cfg.mesh) and not linked(mesh.session):
            raise unreachable(cfg.mesh, cfg.listen_s, "listened")
        snap = fleet.snapshot(time.time_ns())
        # A landed vehicle publishes once a second (comms/state_rate.py): a short listen may
        # hold one state of it (or none) and no rate. Listen on, two idle periods at most.
        end_s = time.monotonic() + 2 * MAX_IDLE_PERIOD_S + 0.5
        while any(v.alive and not v.rate_hz for v in snap.vehicles):
            if time.monotonic() > end_s or (stop is not None and stop.is_set()):
                break
            time.sleep(0.1)
            snap = fleet.snapshot(time.time_ns())
        stations = sorted(pres.ground_stations)
        refused = mesh.stats.states_refused
    out(format_status(snap) if snap.vehicles else "no vehicles on the mesh")
    if snap.unverified_present:
        out(f"{snap.unverified_present:,} presence tokens of unverified vehicles (not listed)")
    if refused:
        out(
            f"SECURITY: {refused} states refused (forged, replayed or unsigned); "
            f"unverified: {', '.join(str(v.vehicle_id) for v in snap.vehicles if v.unverified) or 'none'}"
        )
    out(f"ground stations: {', '.join(map(str, stations)) or 'none'}")
    return 0 if snap.vehicles else 1


def status_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="covey status", description="print the fleet: presence, last state, link age"
    )
    add_mesh_args(p)
    p.add_argument(
        "--listen-s",
        type=finite("seconds"),
        default=1.5,
        help="how long to listen first (default 1.5 s)",
    )
    return p


def status_cli(argv: list[str] | None = None) -> int:
    p = status_parser()
    args = p.parse_args(argv)
    if not 0.1 <= args.listen_s <= 60:
        p.error("--listen-s must be within 0.1..60")
    cfg = StatusConfig(mesh=mesh_config(args, p), listen_s=args.listen_s, key_file=args.key_file)
    try:
        with stop_on_signals() as stop:
            return status_main(cfg, stop=stop)
    except MeshUnreachable as exc:  # nobody at --connect: one line, exit 1
        return nobody_answered(p, exc)
    except ValueError as exc:  # FleetKeyError, MeshConfigError: one line, exit 2
        die(p, str(exc))


# -- covey cmd ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class CmdConfig:
    """One command to send."""

    mesh: MeshConfig
    """How to join the mesh."""
    request: CommandRequest
    """The validated command."""
    targets: tuple[int, ...]
    """Vehicle ids; () = every vehicle present."""
    timeout_s: float = 3.0
    """How long to wait for the acks."""
    discover_s: float = 1.0
    """For `--to all`: how long to wait for presence to learn who should answer."""
    source_id: int = 1
    """Source id written into the command."""
    key_file: str | None = None
    """The station's member key file that signs the command; None: $COVEY_FLEET_KEY_FILE, else
    open mode."""


def format_result(res: CommandResult) -> str:
    lines = []
    for vid in sorted(res.outcomes):
        o = res.outcomes[vid]
        lines.append(f"vehicle {vid:>5}: {o.status.value:<8} {o.reason}".rstrip())
    lines += [f"error: {e}" for e in res.errors]
    return "\n".join(lines) or "no vehicle answered"


def cmd_main(
    cfg: CmdConfig, out: Callable[[str], None] = print, stop: threading.Event | None = None
) -> int:
    """Send the command and print every answer. Raises MeshUnreachable, before sending
    anything, when no router or peer answered at cfg.mesh.connect (within timeout_s)."""
    auth = load_auth(cfg.key_file, fleet=cfg.mesh.fleet)
    with Mesh(cfg.mesh, auth=auth, stop=stop, wait_s=cfg.timeout_s) as mesh:
        if expects_answer(cfg.mesh) and not wait_linked(mesh.session, cfg.timeout_s, stop):
            raise unreachable(cfg.mesh, cfg.timeout_s)
        pres = mesh.presence()
        if not cfg.targets:
            # Wait until presence is quiet: no new vehicle for a while, bounded by discover_s.
            pres.wait_for(lambda v, _g: False, timeout_s=cfg.discover_s)
        else:
            # A fresh session learns the mesh in a few ms: wait (bounded) until every target is
            # seen, so a present vehicle is not reported unreachable because we were too quick.
            wanted = set(cfg.targets)
            pres.wait_for(lambda v, _g: wanted <= set(v), timeout_s=cfg.discover_s)
        present = pres.vehicles
        res = dispatch.send(
            mesh,
            cfg.request,
            cfg.targets,
            present=present,
            source_id=cfg.source_id,
            timeout_s=cfg.timeout_s,
        )
    ignored = 0 if cfg.targets else len(present - dispatch.expected_for_all(present, auth))
    out(f"{cfg.request.describe()}:")
    out(format_result(res))
    if ignored:
        out(f"ignored {ignored:,} presence tokens of vehicles outside the fleet roster")
    bad = [o for o in res.outcomes.values() if o.status is not OutcomeStatus.ACCEPTED]
    return 0 if res.outcomes and not bad else 1


def _request(args: argparse.Namespace) -> CommandRequest:
    verb = args.verb
    if verb == "takeoff":
        return inputs.takeoff(args.alt_m)
    if verb == "goto":
        return inputs.goto_local(args.north_m, args.east_m, args.alt_m, limit_m=100_000.0)
    if verb == "goto-global":
        return inputs.goto_global(args.lat_deg, args.lon_deg, args.alt_amsl_m)
    return inputs.simple(CommandKind[verb.upper()])


_PARAM_HELP = {
    "alt_m": "altitude in metres above the fleet origin, up (as the station's form)",
    "north_m": "metres north of the fleet origin",
    "east_m": "metres east of the fleet origin",
    "lat_deg": "latitude in degrees (WGS-84)",
    "lon_deg": "longitude in degrees (WGS-84)",
    "alt_amsl_m": "altitude in metres above mean sea level",
}
"""Each positional value with its unit and datum (one altitude convention: up, metres)."""


def cmd_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="covey cmd", description="send one command and print every vehicle's ack"
    )
    sub = p.add_subparsers(dest="verb", required=True, metavar="VERB")
    verbs = {
        "takeoff": ("take off to ALT_M metres above the fleet origin", ["alt_m"]),
        "land": ("land where you are", []),
        "hold": ("hold position", []),
        "return": ("return to the start position", []),
        "goto": (
            "fly to NORTH_M, EAST_M of the fleet origin, ALT_M above it (up)",
            ["north_m", "east_m", "alt_m"],
        ),
        "goto-global": (
            "fly to a WGS-84 position, ALT_AMSL_M above mean sea level",
            ["lat_deg", "lon_deg", "alt_amsl_m"],
        ),
        "kill": ("motors off NOW (the vehicle falls); asks to confirm", []),
    }
    for verb, (text, params) in verbs.items():
        sp = sub.add_parser(verb, help=text, description=text)
        for name in params:
            sp.add_argument(name, type=str, help=_PARAM_HELP[name])
        sp.add_argument("--to", required=True, help="vehicle ids (1,2,5 or 1-4) or 'all'")
        sp.add_argument(
            "--timeout-s", type=float, default=3.0, help="seconds to wait for acks (default 3)"
        )
        renamed(sp, {"--timeout": "--timeout-s"})
        add_mesh_args(sp)
        if verb == "kill":
            sp.add_argument("--yes", action="store_true", help="do not ask for confirmation")
    formation_cmd.add_parser(sub)
    return p


def cmd_cli(argv: list[str] | None = None, stdin=None) -> int:
    p = cmd_parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    # argparse takes "-inf" / "-nan" for unknown options and then asks for the missing
    # coordinate; say what is really wrong instead.
    for token in argv:
        if token.lower().lstrip("-") in ("inf", "infinity", "nan") and token.startswith("-"):
            p.error(f"{token}: coordinates and altitudes must be finite numbers")
    args = p.parse_args(argv)
    if args.verb == "formation":
        return _formation(p, args)
    # Negative numbers after a verb (goto 10 0 -5) are positional values, which argparse handles
    # because no option of ours looks like a number.
    try:
        req = _request(args)
        targets = inputs.targets(args.to)
    except InputError as exc:  # one line naming the flag, not the parent's usage
        die(p, f"{args.verb}: " + str(exc).replace("Targets:", "--to", 1))
    if not 0.1 <= args.timeout_s <= 60:
        p.error(f"--timeout-s {args.timeout_s} must be within 0.1..60 s")
    cfg = CmdConfig(
        mesh=mesh_config(args, p),
        request=req,
        targets=targets,
        timeout_s=args.timeout_s,
        key_file=args.key_file,
    )
    if args.verb == "kill" and not args.yes:
        who = "ALL vehicles" if not targets else "vehicle(s) " + ",".join(map(str, targets))
        print(
            f"KILL {who}: motors stop and the vehicles fall. Type 'kill' to confirm: ",
            end="",
            flush=True,
        )
        answer = (stdin or sys.stdin).readline().strip().lower()
        if answer != "kill":
            print("not confirmed; nothing sent", file=sys.stderr)
            return 1
    try:
        with stop_on_signals() as stop:
            return cmd_main(cfg, stop=stop)
    except MeshUnreachable as exc:  # nobody at --connect: one line, exit 1, nothing sent
        return nobody_answered(p, exc)
    except ValueError as exc:  # FleetKeyError, MeshConfigError: one line, exit 2
        die(p, str(exc))


def _formation(p: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    """`covey cmd formation`: a bad value or a refused formation is one line, exit 2, nothing
    sent (groundstation/formation_cmd.py)."""
    if not 0.1 <= args.timeout_s <= 60:
        p.error(f"--timeout-s {args.timeout_s} must be within 0.1..60 s")
    try:
        cfg = formation_cmd.config_of(args, mesh_config(args, p))
        with stop_on_signals() as stop:
            return formation_cmd.formation_main(cfg, stop=stop)
    except MeshUnreachable as exc:  # nobody at --connect: one line, exit 1, nothing sent
        return nobody_answered(p, exc)
    except ValueError as exc:  # FormationError, InputError, BadFileError, FleetKeyError
        die(p, "formation: " + str(exc).replace("Targets:", "--to", 1))
