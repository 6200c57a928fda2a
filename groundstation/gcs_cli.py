"""`covey gcs`: the browser ground station on an existing mesh.

The page needs a login: open the URL it prints (it carries a login token), or, with
--password-file, log in as an operator account (write one with --hash-password NAME).
"""

from __future__ import annotations

import argparse
import getpass
import secrets
import sys

from cli.options import add_mesh_args, die, key_file_path, mesh_config, port, stop_on_signals
from comms.schema import Role
from groundstation.station import GcsConfig, GroundStation, web_exposure_problem, web_host_problem
from groundstation.web_auth import NAME_RE, hash_password, parse_origin, read_password_file
from groundstation.web_proxy import tls_context
from trust.identity import read_member_key


def main(cfg: GcsConfig) -> int:
    with stop_on_signals() as stop, GroundStation(cfg, stop=stop) as gcs:
        if cfg.insecure_http:
            print(
                f"covey gcs: WARNING: plain HTTP on {cfg.host} (--insecure-http): anyone on the "
                "network path can read the login and the session cookie and send commands as you",
                flush=True,
            )
        if cfg.port and gcs.port != cfg.port:
            print(f"covey gcs: port {cfg.port} is busy; using {gcs.port}", flush=True)
        print(
            f"covey gcs: open {gcs.url}  (fleet {cfg.mesh.fleet}, station id {cfg.gcs_id}, Ctrl-C to stop)",
            flush=True,
        )
        while not stop.wait(0.5):
            pass
    return 0


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="covey gcs", description=__doc__)
    add_mesh_args(p)
    p.add_argument(
        "--host", default="127.0.0.1", help="web address to listen on (default: 127.0.0.1)"
    )
    p.add_argument(
        "--port", type=port, default=8080, help="web port (default: 8080; next free if busy)"
    )
    web = p.add_argument_group("web login (the page needs one; see docs/security.md)")
    web.add_argument(
        "--password-file",
        metavar="FILE",
        help="operator accounts, one 'name:<scrypt hash>' line each (mode 600; write lines with "
        "--hash-password): log in by name and password instead of the printed token",
    )
    web.add_argument(
        "--token-label",
        default=None,
        help="operator name of a token login, shown with every command it sends (default: "
        "your user name)",
    )
    web.add_argument(
        "--allow-origin",
        action="append",
        default=[],
        metavar="URL",
        type=_origin,
        help="another origin allowed to open the station's websocket (a reverse proxy's "
        "https://host[:port]); repeatable",
    )
    web.add_argument("--certfile", metavar="PEM", help="TLS certificate: serve HTTPS/WSS")
    web.add_argument("--keyfile", metavar="PEM", help="the certificate's private key")
    web.add_argument(
        "--insecure-http",
        action="store_true",
        help="allow plain HTTP on a non-loopback --host: the login token, the session cookie and "
        "every command cross the network readable and alterable (use TLS instead)",
    )
    web.add_argument(
        "--hash-password",
        metavar="NAME",
        help="print a password file line for operator NAME (asks for the password; reads one "
        "line from stdin when it is not a terminal) and exit",
    )
    p.add_argument(
        "--gcs-id",
        type=int,
        default=None,
        help="this station's id on the mesh (default: random in 2..65000, so that two stations "
        "never share a liveliness token)",
    )
    p.add_argument(
        "--geofence-radius-m", type=float, default=50.0, help="geofence radius drawn (default: 50)"
    )
    p.add_argument(
        "--link",
        default="perfect",
        help="emulated radio link to the vehicles: perfect | xbee | wifi | spec",
    )
    p.add_argument(
        "--every-state",
        action="store_true",
        help="hear every state at its full rate instead of the bounded-rate fleet feed "
        "(small fleets, debugging)",
    )
    return p


def _origin(text: str) -> str:
    try:
        return parse_origin(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _hash_password_line(p: argparse.ArgumentParser, name: str) -> int:
    if not NAME_RE.fullmatch(name):
        die(p, f"--hash-password {name!r}: use 1-64 letters, digits and ._@-")
    if sys.stdin.isatty():
        password = getpass.getpass(f"password for {name}: ")
        if getpass.getpass("again: ") != password:
            die(p, "the passwords differ")
    else:
        password = sys.stdin.readline().rstrip("\r\n")
    if len(password) < 8:
        die(p, "a password needs at least 8 characters")
    print(f"{name}:{hash_password(password)}")
    return 0


def cli(argv: list[str] | None = None) -> int:
    p = parser()
    args = p.parse_args(argv)
    if args.hash_password is not None:
        return _hash_password_line(p, args.hash_password)
    label = args.token_label if args.token_label is not None else _user_name()
    if not NAME_RE.fullmatch(label):
        die(p, f"--token-label {label!r}: use 1-64 letters, digits and ._@-")
    web = dict(
        host=args.host,
        token_label=label,
        password_file=args.password_file,
        allow_origins=tuple(args.allow_origin),
        certfile=args.certfile,
        keyfile=args.keyfile,
        insecure_http=args.insecure_http,
    )
    problem = web_host_problem(args.host) or web_exposure_problem(GcsConfig(**web))
    if problem:  # one line, before anything joins the mesh
        die(p, problem)
    try:
        if args.password_file:
            read_password_file(args.password_file)
        if args.certfile and args.keyfile:
            tls_context(args.certfile, args.keyfile)
    except ValueError as exc:
        die(p, str(exc))
    key = None
    try:
        if (path := key_file_path(args)) is not None:
            key = read_member_key(path)
    except ValueError as exc:
        die(p, str(exc))
    if key is not None:
        if key.role is not Role.STATION:
            die(p, f"--key-file is {key.name}'s key: a ground station needs a station key")
        if args.gcs_id is None:
            args.gcs_id = key.member_id
        elif args.gcs_id != key.member_id:
            die(p, f"--gcs-id {args.gcs_id} but --key-file is {key.name}'s key")
    if args.gcs_id is None:
        args.gcs_id = secrets.randbelow(64999) + 2
    if not 1 <= args.gcs_id <= 65000:
        p.error(f"--gcs-id {args.gcs_id} must be within 1..65000")
    if not 0 < args.geofence_radius_m < 100_000:
        p.error("--geofence-radius-m must be positive")
    try:
        from comms.link import parse_link_spec

        parse_link_spec(args.link)
    except ValueError as exc:
        p.error(f"--link: {exc}")
    cfg = GcsConfig(
        mesh=mesh_config(args, p),
        port=args.port,
        gcs_id=args.gcs_id,
        geofence_radius_m=args.geofence_radius_m,
        link=args.link,
        key_file=args.key_file,
        every_state=args.every_state,
        **web,
    )
    try:
        return main(cfg)
    except ValueError as exc:  # FleetKeyError (key file), MeshConfigError (Zenoh config, port)
        die(p, str(exc))


def _user_name() -> str:
    """The local user's name as an operator name ("operator" if it is not one)."""
    try:
        name = getpass.getuser()
    except (KeyError, OSError):
        return "operator"
    return name if NAME_RE.fullmatch(name) else "operator"


if __name__ == "__main__":
    sys.exit(cli())
