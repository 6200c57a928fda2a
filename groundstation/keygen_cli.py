"""`covey keygen`: the fleet authority's tool (comms/authority.py does the work).

    covey keygen init   [--dir D] [--fleet NAME]     authority key + empty signed roster (v1)
    covey keygen add    [--dir D] vehicle 3          key file for vehicle 3; roster version +1
    covey keygen add    [--dir D] station 1          key file for ground station 1
    covey keygen revoke [--dir D] station 1          drop a member; roster version +1
    covey keygen list   [--dir D]                    print the roster
    covey keygen push   [--dir D] [mesh options]     publish the roster to a running fleet

Give each process its own file: `covey agent --id 3 --key-file vehicle-3.key`,
`covey gcs --gcs-id 1 --key-file station-1.key`. The authority key never leaves the operator.
"""

from __future__ import annotations

import argparse
import sys
import time

from comms.authority import AUTHORITY, DEFAULT_DIR, ROSTER, Authority
from comms.cli_options import add_mesh_args, die, mesh_config, refuse
from comms.identity import FleetKeyError
from comms.schema import MAX_VEHICLE_ID, Role

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
            add_mesh_args(sp, key_file=False)
            refuse(
                sp,
                "--key-file",
                "the roster is signed by the authority key in --dir; a member key adds nothing",
                show=True,
            )
            sp.add_argument(
                "--duration-s",
                type=float,
                default=2.0,
                help="keep re-publishing this long while peers connect (default 2)",
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
        if args.verb == "add":
            path = auth.add(role, args.id)
            print(
                f"{args.role} {args.id}: key file {path} (mode 0600; copy it to that {args.role} "
                f"only); roster v{auth.roster.version}"
            )
        elif args.verb == "revoke":
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
    from comms.mesh import Mesh

    if not 0 <= args.duration_s <= 60:
        p.error("--duration-s must be within 0..60")
    args.fleet = auth.fleet
    cfg = mesh_config(args, p)
    try:
        with Mesh(cfg) as mesh:
            deadline = time.monotonic() + args.duration_s
            while True:  # re-put a few times: peers may still be connecting
                mesh.publish_roster(auth.roster)
                if time.monotonic() >= deadline:
                    break
                time.sleep(0.25)
    except ValueError as exc:  # MeshConfigError: busy port, bad config
        die(p, str(exc))
    print(
        f"pushed fleet {auth.fleet} roster v{auth.roster.version} ({len(auth.roster.members)} members)"
    )
    return 0
