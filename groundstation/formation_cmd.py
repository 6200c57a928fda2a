"""`covey cmd formation`: put vehicles into a shape from a terminal.

    covey cmd formation circle --spacing-m 6 --center-ne-m 20,0 --alt-m 10 --to all
    covey cmd formation line --spacing-m 5 --center-ne-m 40,0 --alt-m 10 --heading-deg 90 --to 1-8
    covey cmd formation file --slots slots.json --center-ne-m 0,0 --alt-m 12 --to all --dry-run

It listens to the fleet's feed for the vehicles' positions, computes the slots and the
assignment (groundstation/formation.py), prints the assignment, then sends one goto per vehicle
through the ordinary command path (groundstation/dispatch.py) and prints every ack. Refusals
(slots too close, more slots than vehicles, a slot outside the fence, a vehicle not heard, a
slot its vehicle would refuse as nearer a keep-out zone than its filter keeps at the position
sigma it reports, slots moved off a zone that end nearer each other than the spacing) are one
line, exit 2, and nothing is sent. A slot its vehicle would move (within the arrival radius) is
sent moved, and the assignment says so. The assignment is remembered in a small state file, so
that the same formation moved (a new centre, heading or altitude) keeps each vehicle's slot.
"""

from __future__ import annotations

import argparse
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from cli.options import add_mesh_args, finite, floats
from comms.commands import CommandResult, OutcomeStatus
from comms.mesh import Mesh
from comms.plan import FleetPlan
from comms.plan_sync import START_PULL_S, PlanSync
from comms.session import MeshConfig, expects_answer, unreachable, wait_linked
from groundstation import dispatch, inputs
from groundstation.fleet import FleetConfig, FleetModel
from groundstation.formation import (
    SHAPES,
    FormationError,
    FormationMemory,
    FormationPlan,
    FormationSpec,
    plan_formation,
)
from trust.auth import load_auth

MAX_STATE_FILE_BYTES = 1 << 20
"""A formation state file larger than this is ignored (a fresh memory)."""


def default_state_file() -> str:
    """Where `covey cmd formation` remembers assignments: $XDG_STATE_HOME/covey/formations.json."""
    base = os.environ.get("XDG_STATE_HOME") or os.path.join(Path.home(), ".local", "state")
    return os.path.join(base, "covey", "formations.json")


@dataclass(frozen=True)
class FormationCmdConfig:
    """One formation to send."""

    mesh: MeshConfig
    """How to join the mesh."""
    spec: FormationSpec
    """The shape, spacing, centre, altitude and heading."""
    targets: tuple[int, ...]
    """Vehicle ids; () = every vehicle present."""
    separation_m: float = FleetConfig().separation_m
    """Slots closer than this are refused (the fleet's separation); the zone clearance the
    vehicles' filters keep is checked at it too (groundstation/target_check.py)."""
    plan: FleetPlan | None = None
    """The fleet plan whose fence and keep-out zones refuse slots; None: the fleet's, pulled
    from the mesh (none there: the vehicles' own checks alone)."""
    dry_run: bool = False
    """Print the assignment only; send nothing."""
    reassign: bool = False
    """Assign anew even if this formation was flown before (else a moved formation keeps slots)."""
    state_file: str | None = None
    """Where assignments are remembered; None: none is (every formation is assigned anew)."""
    timeout_s: float = 3.0
    """How long to wait for each vehicle's ack."""
    discover_s: float = 1.5
    """How long to wait for presence and the vehicles' positions."""
    source_id: int = 1
    """Source id written into the commands."""
    key_file: str | None = None
    """The station's member key file that signs the commands; None: open mode."""


def _load_memory(path: str | None) -> FormationMemory:
    if path is None:
        return FormationMemory()
    try:
        p = Path(path)
        if p.stat().st_size > MAX_STATE_FILE_BYTES:
            return FormationMemory()
        return FormationMemory.from_json(p.read_text("utf-8"))
    except (OSError, UnicodeDecodeError):
        return FormationMemory()


def _save_memory(path: str | None, memory: FormationMemory) -> None:
    if path is None:
        return
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_suffix(".tmp")
    tmp.write_text(memory.to_json(), "utf-8")
    tmp.replace(p)


def send_formation(
    mesh: Mesh,
    fp: FormationPlan,
    *,
    present: set[int],
    source_id: int,
    timeout_s: float,
    on_built=None,
) -> list[CommandResult]:
    """One goto per vehicle of `fp` to its slot (the command path every goto takes)."""
    results = []
    for vid, (n_m, e_m, down_m) in zip(fp.vehicle_ids, fp.targets_ned_m.tolist(), strict=True):
        req = inputs.goto_local(n_m, e_m, -down_m, limit_m=100_000.0)
        results.append(
            dispatch.send(
                mesh,
                req,
                (vid,),
                present=present,
                source_id=source_id,
                timeout_s=timeout_s,
                on_built=on_built,
            )
        )
    return results


def formation_main(
    cfg: FormationCmdConfig,
    out: Callable[[str], None] = print,
    stop: threading.Event | None = None,
) -> int:
    """Listen for positions, plan, print the assignment, send (unless dry_run), print the acks.
    Raises FormationError (nothing sent) and MeshUnreachable (before anything is sent)."""
    auth = load_auth(cfg.key_file, fleet=cfg.mesh.fleet)
    fleet = FleetModel(FleetConfig(verified_only=auth is not None))
    with Mesh(cfg.mesh, auth=auth, stop=stop, wait_s=cfg.timeout_s) as mesh:
        if expects_answer(cfg.mesh) and not wait_linked(mesh.session, cfg.timeout_s, stop):
            raise unreachable(cfg.mesh, cfg.timeout_s)
        mesh.subscribe_feed(fleet.on_state, on_refused=fleet.on_state_refused)
        pres = mesh.presence()
        wanted = set(cfg.targets)
        if wanted:
            pres.wait_for(lambda v, _g: wanted <= set(v), timeout_s=cfg.discover_s)
        else:
            pres.wait_for(lambda v, _g: False, timeout_s=cfg.discover_s)
        present = set(pres.vehicles)
        ids = wanted or dispatch.expected_for_all(present, auth)
        positions, sigmas = _positions(fleet, ids, cfg.discover_s, stop)
        memory = _load_memory(cfg.state_file)
        plan = cfg.plan
        if plan is None:  # the fleet's plan, as the vehicles hold it (comms/plan_sync.py)
            with PlanSync(mesh.session, cfg.mesh.fleet, auth) as sync:
                sync.pull_now(START_PULL_S)
                plan = sync.plan
        fp = plan_formation(
            cfg.spec,
            positions,
            cfg.separation_m,
            plan=plan,
            memory=memory,
            reassign=cfg.reassign,
            pos_sigma_m=sigmas,
        )
        s = cfg.spec
        out(
            f"formation {s.shape} spacing {s.spacing_m:g} m, centre N {s.center_ne_m[0]:g} "
            f"E {s.center_ne_m[1]:g}, alt {s.alt_m:g} m, heading {s.heading_deg:g} deg, "
            f"{len(fp.vehicle_ids)} vehicles ("
            + ("slots kept from the last time it flew" if fp.kept else "optimal assignment")
            + "):"
        )
        for line in fp.lines():
            out(line)
        if cfg.dry_run:
            out("dry run: nothing sent")
            return 0
        results = send_formation(
            mesh, fp, present=present, source_id=cfg.source_id, timeout_s=cfg.timeout_s
        )
    _save_memory(cfg.state_file, memory)
    bad = 0
    for res in results:
        for vid in sorted(res.outcomes):
            o = res.outcomes[vid]
            bad += o.status is not OutcomeStatus.ACCEPTED
            out(f"vehicle {vid:>5}: {o.status.value:<8} {o.reason}".rstrip())
        for e in res.errors:
            bad += 1
            out(f"error: {e}")
    return 0 if results and not bad else 1


def _positions(
    fleet: FleetModel, ids: set[int], wait_s: float, stop: threading.Event | None
) -> tuple[dict[int, tuple[float, float, float] | None], dict[int, float]]:
    """Each vehicle's latest position from the feed, waiting (bounded) until all are heard, and
    the position 1-sigma those states report (the goal rule pads zones by it)."""
    end_s = time.monotonic() + wait_s
    while True:
        snap = fleet.snapshot(time.time_ns(), trails=False)
        seen = {v.vehicle_id: v.state for v in snap.vehicles if v.state is not None}
        if ids <= set(seen) or time.monotonic() > end_s or (stop is not None and stop.is_set()):
            return (
                {vid: seen[vid].pos_ned_m if vid in seen else None for vid in ids},
                {vid: seen[vid].pos_sigma_m for vid in ids if vid in seen},
            )
        time.sleep(0.05)


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """`formation` under `covey cmd`'s verbs."""
    text = "put vehicles into a shape: one goto each, to the slots of an optimal assignment"
    sp = sub.add_parser("formation", help=text, description=text)
    sp.add_argument("shape", choices=SHAPES, help="the shape ('file': slots from --slots FILE)")
    sp.add_argument(
        "--spacing-m",
        type=finite("metres", minimum=0.0),
        default=0.0,
        help="distance between neighbouring slots (not for 'file')",
    )
    sp.add_argument(
        "--center-ne-m",
        type=lambda t: floats(t, 2, "--center-ne-m"),
        required=True,
        metavar="N,E",
        help="centre of the shape, metres north and east of the fleet origin",
    )
    sp.add_argument(
        "--alt-m", type=float, required=True, help="altitude above the fleet origin (up)"
    )
    sp.add_argument(
        "--heading-deg",
        type=float,
        default=0.0,
        help="where the shape faces, degrees clockwise from north (default 0)",
    )
    sp.add_argument("--slots", metavar="FILE", help='JSON {"slots_fr_m": [[forward, right], ...]}')
    sp.add_argument(
        "--separation-m",
        type=finite("metres", minimum=0.0),
        default=FleetConfig().separation_m,
        help="refuse slots closer than this (default: the fleet's separation, "
        f"{FleetConfig().separation_m:g} m)",
    )
    sp.add_argument("--dry-run", action="store_true", help="print the assignment, send nothing")
    sp.add_argument(
        "--reassign",
        action="store_true",
        help="assign anew even if this formation flew before (default: a moved one keeps slots)",
    )
    sp.add_argument(
        "--state-file",
        default=None,
        help=f"where assignments are remembered (default {default_state_file()})",
    )
    sp.add_argument("--to", required=True, help="vehicle ids (1,2,5 or 1-4) or 'all'")
    sp.add_argument(
        "--timeout-s", type=float, default=3.0, help="seconds to wait for acks (default 3)"
    )
    add_mesh_args(sp)
    return sp


def config_of(args: argparse.Namespace, mesh: MeshConfig) -> FormationCmdConfig:
    """The config `covey cmd formation`'s options describe; FormationError/InputError/BadFileError
    (one line) for a bad value."""
    from groundstation.formation import load_slots

    slots = load_slots(args.slots) if args.slots else ()
    spec = FormationSpec(
        args.shape,
        args.spacing_m,
        tuple(args.center_ne_m),
        args.alt_m,
        args.heading_deg,
        slots,
    )
    return FormationCmdConfig(
        mesh=mesh,
        spec=spec,
        targets=inputs.targets(args.to),
        separation_m=args.separation_m,
        dry_run=args.dry_run,
        reassign=args.reassign,
        state_file=args.state_file or default_state_file(),
        timeout_s=args.timeout_s,
        key_file=args.key_file,
    )


__all__ = ["FormationError", "add_parser", "config_of", "formation_main", "send_formation"]
