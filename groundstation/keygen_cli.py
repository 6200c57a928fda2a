"""`covey keygen`: the fleet authority's tool (trust/authority.py does the work).

    covey keygen init   [--dir D] [--fleet NAME]     authority key + empty signed roster (v1)
    covey keygen add    [--dir D] vehicle 3          key file for vehicle 3; roster version +1
    covey keygen add    [--dir D] station 1          key file for ground station 1
    covey keygen revoke [--dir D] station 1          drop a member; roster version +1
    covey keygen list   [--dir D]                    print the roster
    covey keygen push   [--dir D] [mesh options]     publish the roster to a running fleet, and
                                                     say how many members confirmed they hold it

Give each process its own file, by the path `add` prints: `covey agent --id 3 --key-file
~/.config/covey/fleet/vehicle-3.key`, `covey gcs --key-file ~/.config/covey/fleet/station-1.key`.
The authority key never leaves the operator. `push` is a Zenoh client of the router at
--connect (give --zenoh-config a station's TLS config on a secured mesh: `covey tls init`).
"""

from __future__ import annotations

import argparse
import sys

from cli.options import (
    add_mesh_args,
    die,
    mesh_config,
    nobody_answered,
    refuse,
)
from comms.schema import MAX_VEHICLE_ID, Role
from trust.authority import AUTHORITY, DEFAULT_DIR, ROSTER, Authority
from trust.identity import FleetKeyError

VERBS = {
    "init": "create the fleet authority key and an empty signed roster",
    "add": "enrol a vehicle or station: write its key file, re-sign the roster",
    "revoke": "drop a vehicle or station from the roster (then push it to a running fleet)",
    "list": "print the roster",
    "push": "publish the current roster to a running fleet (members apply it at once)",
}


def keygen_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="covey keygen",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = p.add_subparsers(dest="verb", required=True, metavar="VERB")
    for verb, text in VERBS.items():
        sp = sub.add_parser(verb, help=text, description=text)
        sp.add_argument(
            "--dir",
            default=str(DEFAULT_DIR),
            help=f"the authority's directory (default {DEFAULT_DIR})",
        )
        if verb == "init":
            sp.add_argument("--fleet", default="covey", help="fleet name (default covey)")
        if verb in ("add", "revoke"):
            sp.add_argument("role", choices=("vehicle", "station"), help="what the member is")
            sp.add_argument("id", type=int, help=f"vehicle id or station id, 1..{MAX_VEHICLE_ID}")
        if verb == "push":
            add_mesh_args(
                sp,
                key_file=False,
                mode_default="client",
                mode_help="default: client, of the router or station at --connect; "
                "peer: join a peer mesh",
            )
            refuse(
                sp,
                "--key-file",
                "the roster is signed by the authority key in --dir; a member key adds nothing",
                show=True,
            )
            sp.add_argument(
                "--duration-s",
                type=float,
                default=5.0,
                help="re-publish until a member confirms it holds the roster, at most this "
                "long (default 5); nobody confirming is exit status 1",
            )
    return p


def keygen_cli(argv: list[str]) -> int:
    p = keygen_parser()
    args = p.parse_args(argv)
    role = Role[args.role.upper()] if getattr(args, "role", None) else None
    if role is not None and not 1 <= args.id <= MAX_VEHICLE_ID:
        p.error(f"id {args.id} must be within 1..{MAX_VEHICLE_ID}")
    try:
        if args.verb == "init":
            auth = Authority.init(args.dir, args.fleet)
            print(
                f"fleet {auth.fleet}: authority key {auth.dir / AUTHORITY} (mode 0600; keep it off "
                f"the vehicles), roster v1 at {auth.dir / ROSTER}"
            )
            return 0
        auth = Authority(args.dir)
        if args.verb in ("add", "revoke") and role is None:
            die(p, f"{args.verb} needs a role")
        if args.verb == "add" and role is not None:
            path = auth.add(role, args.id)
            print(
                f"{args.role} {args.id}: key file {path} (mode 0600; copy it to that {args.role} "
                f"only); roster v{auth.roster.version}"
            )
        elif args.verb == "revoke" and role is not None:
            auth.revoke(role, args.id)
            print(
                f"{args.role} {args.id} revoked: roster v{auth.roster.version}; `covey keygen push` "
                "applies it to a running fleet"
            )
        elif args.verb == "list":
            r = auth.roster
            print(f"fleet {r.fleet} roster v{r.version}, {len(r.members)} members")
            for m in r.members:
                print(f"  {m.role.name.lower():8s} {m.member_id:5d}  {m.public_key.hex()[:16]}")
        elif args.verb == "push":
            return _push(auth, args, p)
    except (FileExistsError, KeyError) as exc:
        print(f"covey keygen: {exc.args[0] if exc.args else exc}", file=sys.stderr)
        return 1
    except FleetKeyError as exc:
        die(p, str(exc))
    except (OSError, ValueError) as exc:  # ValueError: a NUL byte in a path, a bad fleet name
        print(f"covey keygen: {getattr(exc, 'strerror', None) or exc}", file=sys.stderr)
        return 1
    return 0


def _push(auth: Authority, args: argparse.Namespace, p: argparse.ArgumentParser) -> int:
    from comms.doc_sync import confirmations
    from comms.session import MeshUnreachable
    from groundstation.push import push_and_confirm

    if not 0.5 <= args.duration_s <= 60:
        p.error("--duration-s must be within 0.5..60")
    args.fleet = auth.fleet
    cfg = mesh_config(args, p)
    roster = auth.roster
    what = f"fleet {auth.fleet} roster v{roster.version} ({len(roster.members)} members)"
    try:
        heard = push_and_confirm(
            cfg,
            args.duration_s,
            lambda mesh: mesh.publish_roster(roster),
            lambda session, timeout_s: confirmations(
                session, auth.fleet, roster.version, timeout_s=timeout_s
            ),
        )
    except MeshUnreachable as exc:
        return nobody_answered(p, exc)
    except ValueError as exc:  # MeshConfigError: busy port, bad config
        die(p, str(exc))
    if not heard:
        where = ", ".join(cfg.connect) or "the mesh"
        print(
            f"covey keygen push: published {what} at {where}, but no member confirmed it "
            f"within {args.duration_s:g} s (no keyed member running, or a router that drops "
            "covey/<fleet>/roster: see comms/zenoh_configs)",
            file=sys.stderr,
        )
        return 1
    members = len({c.replier for c in heard})
    newer = max(c.version for c in heard)
    note = f"; the fleet holds v{newer}, newer than {auth.dir}'s" if newer > roster.version else ""
    print(f"pushed {what}: {members} member(s) confirmed they hold it{note}")
    return 0
