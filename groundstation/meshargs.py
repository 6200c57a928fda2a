"""Command-line options for joining a mesh, shared by `covey gcs`, `covey status` and `covey cmd`."""

from __future__ import annotations

import argparse
import sys
from typing import NoReturn

from comms.session import DEFAULT_PORT, MeshConfig


def die(parser: argparse.ArgumentParser, message: str) -> NoReturn:
    """A set-up error (key file, roster, Zenoh config, endpoint): one line, exit status 2."""
    print(f"{parser.prog}: error: {' '.join(message.split())}", file=sys.stderr)
    raise SystemExit(2)


def add_mesh_args(parser: argparse.ArgumentParser, key_file: bool = True) -> None:
    g = parser.add_argument_group("mesh")
    g.add_argument("--fleet", default="covey", help="fleet name (default: covey)")
    g.add_argument(
        "--connect",
        action="append",
        default=None,
        metavar="ENDPOINT",
        help=f"endpoint to connect to, repeatable (default: tcp/127.0.0.1:{DEFAULT_PORT}; "
        "`covey demo` prints its own)",
    )
    g.add_argument(
        "--mesh-mode",
        choices=("peer", "client", "router"),
        default="peer",
        help="Zenoh role of this process (default: peer)",
    )
    g.add_argument(
        "--listen",
        action="append",
        default=None,
        metavar="ENDPOINT",
        help="endpoint to listen on (default: tcp/127.0.0.1:0 for a peer)",
    )
    g.add_argument(
        "--zenoh-config",
        default=None,
        metavar="FILE",
        help="full Zenoh JSON5 config: TLS, user/password, access control (comms/zenoh_configs/)",
    )
    if key_file:
        g.add_argument(
            "--key-file",
            default=None,
            metavar="FILE",
            help="this member's key file (covey keygen add); or $COVEY_FLEET_KEY_FILE. "
            "Without one: OPEN MODE (nothing authenticated; tests only)",
        )


def mesh_config(args: argparse.Namespace, parser: argparse.ArgumentParser) -> MeshConfig:
    """The MeshConfig the options describe; a bad combination is an argparse error."""
    connect = tuple(e for item in (args.connect or []) for e in item.split(",") if e)
    listen = tuple(e for item in (args.listen or []) for e in item.split(",") if e)
    kw: dict = {"fleet": args.fleet, "mode": args.mesh_mode, "config_file": args.zenoh_config}
    if args.connect is not None:
        kw["connect"] = connect
    elif args.mesh_mode == "router":
        kw["connect"] = ()
    if args.listen is not None:
        kw["listen"] = listen
    elif args.mesh_mode == "router":
        kw["listen"] = (f"tcp/127.0.0.1:{DEFAULT_PORT}",)
    try:
        return MeshConfig(**kw)
    except ValueError as exc:
        die(parser, str(exc))
