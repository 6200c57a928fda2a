"""`covey plan`: the fleet plan (fence with floor and ceiling, keep-out zones, home and rally
points) from a file to every vehicle.

    covey plan load FILE [--dir D | --key-file station-1.key] [--origin LAT,LON,ALT]
                         [--floor-m X] [--ceiling-m Y] [--separation-m S] [--out PATH]
                         [--rally-pads N] [--rally-pad-spacing-m M]
        check a GeoJSON or QGC .plan file (home, rally points and the N landing pads M apart a
        return lays around each keep the zone clearance the vehicles' filters keep at
        separation S, inside the fence), sign it (the fleet authority in --dir, or a roster
        station's key) and write the signed plan (default: D/plan.bin)
    covey plan show [FILE] [--dir D] [--origin ...]
        print a signed plan (default D/plan.bin, its signature checked against D's roster) or
        what a GeoJSON / QGC file holds
    covey plan push [--plan PATH] [--dir D] [--separation-m S] [--rally-pads N]
                    [--rally-pad-spacing-m M] [mesh options] [--duration-s S]
        check the signed plan again as load does (a plan signed before a check existed is not
        sent unchecked), publish it to a running fleet and say how many members confirmed it

Give --origin the fleet origin your agents use (`covey agent --origin`): the file's WGS-84
coordinates become local metres around it. Altitudes (floor, ceiling, rally) are metres above
the origin, up. The agents refuse a goto or take-off inside a keep-out zone, outside the fence,
above the ceiling or below the floor, with the reason in the ack (docs/sky.md).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from cli.options import (
    add_mesh_args,
    die,
    finite,
    geo_origin,
    mesh_config,
    nobody_answered,
)
from comms.geo import GeoOrigin
from comms.plan import RALLY_PAD_SPACING_M, RALLY_PADS, FleetPlan, PadLayout
from comms.plan_io import (
    PLAN_FILE,
    BadPlanError,
    PlanGeometry,
    check_geometry,
    next_version,
    read_plan_file,
    read_signed_plan,
    write_signed_plan,
)
from comms.schema import PlanMessage, Role
from groundstation.plan_edit import SEPARATION_M, check_landing
from policy.goal_rule import ASSUMED_POS_SIGMA_M
from trust.authority import DEFAULT_DIR, Authority
from trust.identity import FleetKeyError, public_bytes, verify

VERBS = {
    "load": "check a GeoJSON or QGC .plan file, sign it, write the signed plan",
    "show": "print a signed plan or what a plan file holds",
    "push": "publish the signed plan to a running fleet",
}


def _default_clearance_m() -> float:
    """The zone clearance at the default separation and the assumed position sigma (for --help):
    policy.zone_lines' share of the padded separation plus sigma_k x the sigma."""
    from policy.safety import SafetyConfig
    from policy.zone_lines import ZONE_CLEARANCE_SHARE

    cfg = SafetyConfig(radius_m=SEPARATION_M)
    pad_m = cfg.sigma_k * ASSUMED_POS_SIGMA_M
    return ZONE_CLEARANCE_SHARE * cfg.radius_m * (1.0 + cfg.margin) + pad_m


def plan_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="covey plan",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = p.add_subparsers(dest="verb", required=True, metavar="VERB")
    for verb, text in VERBS.items():
        sp = sub.add_parser(verb, help=text, description=text)
        sp.add_argument(
            "--dir",
            default=str(DEFAULT_DIR),
            help=f"the fleet authority's directory (default {DEFAULT_DIR})",
        )
        if verb in ("load", "show"):
            sp.add_argument(
                "file",
                nargs=None if verb == "load" else "?",
                metavar="FILE",
                help="GeoJSON FeatureCollection or QGC .plan"
                + ("" if verb == "load" else "; or a signed plan (default: DIR/plan.bin)"),
            )
            sp.add_argument(
                "--origin",
                type=geo_origin,
                default=None,
                metavar="LAT,LON,ALT",
                help="fleet origin LAT,LON,ALT (degrees, degrees, m; default: covey's, as "
                "covey agent's)",
            )
        if verb == "load":
            sp.add_argument(
                "--key-file",
                default=None,
                metavar="FILE",
                help="sign as this roster station (its key file) instead of the authority in --dir",
            )
            sp.add_argument(
                "--floor-m", type=float, default=None, help="the fence's floor above the origin"
            )
            sp.add_argument(
                "--ceiling-m",
                type=float,
                default=None,
                help="the fence's ceiling above the origin (a QGC fence has none)",
            )
            sp.add_argument(
                "--out", default=None, metavar="PATH", help="where to write (default DIR/plan.bin)"
            )
        if verb in ("load", "push"):
            sp.add_argument(
                "--separation-m",
                type=finite("metres"),
                default=SEPARATION_M,
                help="the fleet's separation (the agents' --separation-m): home, rally points "
                "and the landing pads around them must keep the zone clearance their filters "
                f"keep at it and a {ASSUMED_POS_SIGMA_M:g} m position sigma (default {SEPARATION_M:g}: "
                f"{_default_clearance_m():.1f} m from a "
                "zone or the fence)",
            )
            sp.add_argument(
                "--rally-pads",
                type=int,
                default=RALLY_PADS,
                help="landing pads a return lays around home and each rally point, a square grid "
                f"(the agents' --rally-pads; default {RALLY_PADS}): each must be inside the "
                "fence and keep that clearance",
            )
            sp.add_argument(
                "--rally-pad-spacing-m",
                type=finite("metres"),
                default=RALLY_PAD_SPACING_M,
                help="distance between those pads (the agents' --rally-pad-spacing-m; default "
                f"{RALLY_PAD_SPACING_M:g})",
            )
        if verb == "push":
            sp.add_argument(
                "--plan",
                default=None,
                metavar="PATH",
                help="the signed plan (default DIR/plan.bin)",
            )
            add_mesh_args(
                sp,
                key_file=False,
                fleet_default=None,
                fleet_help="refused if not the plan's fleet (default: the plan's)",
                mode_default="client",
                mode_help="default: client, of the router or station at --connect; "
                "peer: join a peer mesh",
            )
            sp.add_argument(
                "--duration-s",
                type=float,
                default=5.0,
                help="re-publish until a member confirms it holds the plan, at most this long "
                "(default 5); nobody confirming is exit status 1",
            )
    return p


def plan_cli(argv: list[str]) -> int:
    p = plan_parser()
    args = p.parse_args(argv)
    try:
        if args.verb == "load":
            return _load(args, p)
        if args.verb == "show":
            return _show(args)
        return _push(args, p)
    except (BadPlanError, FleetKeyError) as exc:
        die(p, str(exc))
    except ValueError as exc:  # a geometry check on flags (a floor above the ceiling)
        die(p, str(exc))
    except OSError as exc:
        print(f"covey plan: {exc.strerror or exc}: {exc.filename or ''}", file=sys.stderr)
        return 1


def _origin(args: argparse.Namespace) -> GeoOrigin:
    return args.origin or GeoOrigin()


def check_plan(geometry: PlanGeometry, args: argparse.Namespace, where: str) -> None:
    """The checks a plan passes before `load` signs it and again before `push` sends it
    (BadPlanError naming `where` otherwise): its geometry (comms/plan_io.py `check_geometry`:
    valid polygons, home and rally points inside the fence and outside every zone), then home,
    the rally points and their landing pads (`--rally-pads`, `--rally-pad-spacing-m`) against
    the zones, the fence and the clearance the vehicles' filters keep at `--separation-m`
    (plan_edit.py `check_landing`, the station's editor's)."""
    try:
        pads = PadLayout(args.rally_pads, args.rally_pad_spacing_m)
    except ValueError as exc:
        raise BadPlanError(f"--rally-pads/--rally-pad-spacing-m: {exc}") from None
    try:
        check_geometry(PlanGeometry(geometry.fence, geometry.keep_out, geometry.rally))
        check_landing(geometry, args.separation_m, pads=pads)
    except ValueError as exc:  # EditRefused is one
        raise BadPlanError(f"{where}: {' '.join(str(exc).split())}") from None


def _load(args: argparse.Namespace, p: argparse.ArgumentParser) -> int:
    geometry = read_plan_file(
        args.file, _origin(args), floor_alt_m=args.floor_m, ceiling_alt_m=args.ceiling_m
    )
    check_plan(geometry, args, f"plan file {Path(args.file).expanduser()}")
    out = Path(args.out).expanduser() if args.out else Path(args.dir).expanduser() / PLAN_FILE
    previous = read_signed_plan(out) if out.exists() else None
    if args.key_file is not None:
        from trust.auth import load_auth

        station = load_auth(args.key_file)
        if station is None or station.role is not Role.STATION:
            die(p, f"--key-file {args.key_file} is not a ground station's key: only stations sign")
        plan = _versioned(geometry, station.fleet, previous)
        plan = station.sign_plan(plan)
        signer = f"station {station.member_id}"
    else:
        authority = Authority(args.dir)
        from trust.auth import sign_plan

        plan = sign_plan(authority.key, _versioned(geometry, authority.fleet, previous))
        signer = f"the fleet authority in {authority.dir}"
    if previous is not None and previous.fleet != plan.fleet:
        die(p, f"{out} holds fleet {previous.fleet!r}'s plan, not {plan.fleet!r}'s; give --out")
    write_signed_plan(out, plan)
    for note in geometry.notes:
        print(f"note: {note}")
    print(
        f"fleet {plan.fleet} plan v{plan.version} signed by {signer}: {out} "
        f"({len(PlanMessage(plan).encode())} bytes); `covey plan push` sends it to a running fleet"
    )
    _print_plan(plan)
    return 0


def _versioned(geometry: PlanGeometry, fleet: str, previous: FleetPlan | None) -> FleetPlan:
    now_ns = time.time_ns()
    return geometry.plan(fleet, next_version(previous, now_ns), now_ns)


def _show(args: argparse.Namespace) -> int:
    path = Path(args.file).expanduser() if args.file else Path(args.dir).expanduser() / PLAN_FILE
    raw = path.read_bytes()[:1] if path.is_file() else b""
    if raw == bytes([PlanMessage.TYPE]):
        plan = read_signed_plan(path)
        print(f"fleet {plan.fleet} plan v{plan.version} ({path}): {_signature_note(plan, args)}")
        _print_plan(plan)
        return 0
    geometry = read_plan_file(path, _origin(args))
    for note in geometry.notes:
        print(f"note: {note}")
    print(f"{path}: not signed yet (covey plan load signs it)")
    _print_plan(geometry.plan("unsigned", 1, 0))
    return 0


def _signature_note(plan: FleetPlan, args: argparse.Namespace) -> str:
    """Whether the signature verifies against the authority directory's key and roster."""
    who = "the fleet authority" if plan.signer_id == 0 else f"station {plan.signer_id}"
    try:
        authority = Authority(args.dir)
    except FleetKeyError:
        return f"signed by {who} (not checked: no authority in {args.dir})"
    if authority.fleet != plan.fleet:
        return f"signed by {who} (not checked: {args.dir} is fleet {authority.fleet!r}'s)"
    if plan.signer_id == 0:
        key = authority.key.public_key()
    else:
        member = authority.roster.member(Role.STATION, plan.signer_id)
        if member is None:
            return f"signed by {who}, NOT in roster v{authority.roster.version}: members refuse it"
        from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PublicKey

        key = Ed25519PublicKey.from_public_bytes(member.public_key)
    head = PlanMessage.peek(PlanMessage(plan).encode())
    if verify(key, head.sig, "plan", plan.fleet, head.signed):
        return f"signed by {who}, signature verified ({public_bytes(key).hex()[:12]})"
    return f"signed by {who}: signature does NOT verify; members refuse it"


def _print_plan(plan: FleetPlan) -> None:
    import shapely

    if plan.fence is not None:
        f = plan.fence
        area = shapely.Polygon(f.vertices_ne_m).area
        band = f"floor {_alt(f.floor_alt_m, 'none')}, ceiling {_alt(f.ceiling_alt_m, 'none')}"
        print(f"  fence: {len(f.vertices_ne_m)} vertices, {area:,.0f} m^2, {band}")
    else:
        print("  fence: none (the agents' circular --geofence-radius-m applies)")
    for z in plan.keep_out:
        area = shapely.Polygon(z.vertices_ne_m).area
        band = f"{_alt(z.floor_alt_m, 'the ground')} to {_alt(z.ceiling_alt_m, 'no top')}"
        print(f"  keep-out {z.name!r}: {len(z.vertices_ne_m)} vertices, {area:,.0f} m^2, {band}")
    for r in plan.rally:
        print(f"  {'home' if r.name == 'home' else f'rally {r.name!r}'}: north {r.n_m:.1f} m, "
              f"east {r.e_m:.1f} m, {r.alt_m:g} m up")  # fmt: skip


def _alt(alt_m: float | None, none: str) -> str:
    return none if alt_m is None else f"{alt_m:g} m"


def _push(args: argparse.Namespace, p: argparse.ArgumentParser) -> int:
    from comms.plan_sync import plan_confirmations, publish_plan
    from comms.session import MeshUnreachable
    from groundstation.push import push_and_confirm

    if not 0.5 <= args.duration_s <= 60:
        p.error("--duration-s must be within 0.5..60")
    path = Path(args.plan).expanduser() if args.plan else Path(args.dir).expanduser() / PLAN_FILE
    plan = read_signed_plan(path)
    # signed is not checked: it may predate a check (the pads), or come from another tool
    check_plan(
        PlanGeometry(plan.fence, plan.keep_out, plan.rally),
        args,
        f"{path} (plan v{plan.version}, nothing sent)",
    )
    if args.fleet is not None and args.fleet != plan.fleet:
        die(p, f"--fleet {args.fleet} but {path} is fleet {plan.fleet!r}'s plan")
    args.fleet = plan.fleet
    cfg = mesh_config(args, p)
    what = f"fleet {plan.fleet} plan v{plan.version}"
    try:
        heard = push_and_confirm(
            cfg,
            args.duration_s,
            lambda mesh: publish_plan(mesh.session, plan),
            lambda session, timeout_s: plan_confirmations(
                session, plan.fleet, plan.version, timeout_s=timeout_s
            ),
        )
    except MeshUnreachable as exc:
        return nobody_answered(p, exc)
    except ValueError as exc:  # MeshConfigError: busy port, bad config
        die(p, str(exc))
    if not heard:
        where = ", ".join(cfg.connect) or "the mesh"
        print(
            f"covey plan push: published {what} at {where}, but no member confirmed it within "
            f"{args.duration_s:g} s (no member running, a signer the members do not trust, or "
            "a router that drops covey/<fleet>/plan: see comms/zenoh_configs)",
            file=sys.stderr,
        )
        return 1
    members = len({c.replier for c in heard})
    newer = max(c.version for c in heard)
    note = f"; the fleet holds v{newer}, newer than {path}'s" if newer > plan.version else ""
    print(f"pushed {what}: {members} member(s) confirmed they hold it{note}")
    return 0
