"""Command-line options for joining a mesh, shared by `covey gcs`, `covey status` and `covey cmd`."""

from __future__ import annotations

import argparse

from comms.session import DEFAULT_PORT, MeshConfig


def add_mesh_args(parser: argparse.ArgumentParser) -> None:
    g = parser.add_argument_group("mesh")
    g.add_argument("--fleet", default="covey", help="fleet name (default: covey)")
    g.add_argument("--connect", action="append", default=None, metavar="ENDPOINT",
                   help=f"endpoint to connect to, repeatable (default: tcp/127.0.0.1:{DEFAULT_PORT}; "
                   "`covey demo` prints its own)")  # fmt: skip
    g.add_argument("--mesh-mode", choices=("peer", "client", "router"), default="peer",
                   help="Zenoh role of this process (default: peer)")  # fmt: skip
    g.add_argument("--listen", action="append", default=None, metavar="ENDPOINT",
                   help="endpoint to listen on (default: tcp/127.0.0.1:0 for a peer)")  # fmt: skip
    g.add_argument("--zenoh-config", default=None, metavar="FILE",
                   help="full Zenoh JSON5 config: TLS, user/password, access control "
                   "(comms/zenoh_configs/)")  # fmt: skip
    g.add_argument("--key-file", default=None, metavar="FILE",
                   help="fleet key to sign commands (covey keygen); or $COVEY_FLEET_KEY_FILE / "
                   "$COVEY_FLEET_KEY. Without a key: open mode")  # fmt: skip


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
        parser.error(str(exc))
        raise  # unreachable: parser.error exits
