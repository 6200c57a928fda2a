"""`covey gcs`: the browser ground station on an existing mesh."""

from __future__ import annotations

import argparse
import secrets
import sys

from comms.cli_options import add_mesh_args, die, key_file_path, mesh_config, port, stop_on_signals
from comms.identity import read_member_key
from comms.schema import Role
from groundstation.station import GcsConfig, GroundStation, web_host_problem


def main(cfg: GcsConfig) -> int:
    with stop_on_signals() as stop, GroundStation(cfg) as gcs:
        if cfg.port and gcs.server.get_port() != cfg.port:
            print(f"covey gcs: port {cfg.port} is busy; using {gcs.server.get_port()}", flush=True)
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


def cli(argv: list[str] | None = None) -> int:
    p = parser()
    args = p.parse_args(argv)
    problem = web_host_problem(args.host)
    if problem:  # one line, before anything joins the mesh
        die(p, problem)
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
        host=args.host,
        port=args.port,
        gcs_id=args.gcs_id,
        geofence_radius_m=args.geofence_radius_m,
        link=args.link,
        key_file=args.key_file,
        every_state=args.every_state,
    )
    try:
        return main(cfg)
    except ValueError as exc:  # FleetKeyError (key file), MeshConfigError (Zenoh config, port)
        die(p, str(exc))


if __name__ == "__main__":
    sys.exit(cli())
