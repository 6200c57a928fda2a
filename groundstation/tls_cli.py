"""`covey tls`: the fleet's TLS certificates and Zenoh configs (trust/tls_setup.py does the work).

    covey tls init  [--dir D] --names router gcs-1 vehicle-1 ... [--hosts gcs.local,10.0.0.1]
        fleet CA (made once, then reused), a certificate and key per identity, and ready-to-use
        configs: D/router.json5 for the router, D/gcs-1.json5, D/vehicle-1.json5 for the clients
    covey tls certs OUTDIR NAME... [--hosts ...]
        certificates only (what comms/zenoh_configs/make_certs.sh runs)

Default D: ~/.config/covey/tls. Copy `vehicle-1.pem`, `vehicle-1.key`, `ca.pem` and
`vehicle-1.json5` (with its paths edited) to vehicle 1 only; keep `ca.key` with the operator.
"""

from __future__ import annotations

import argparse

from cli.options import comma_list, die
from trust.tls_setup import DEFAULT_DIR, TlsConfig, TlsSetupError, init, role_of


def tls_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="covey tls",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = p.add_subparsers(dest="verb", required=True, metavar="VERB")
    sp = sub.add_parser(
        "init",
        help="fleet CA, one certificate per identity, and each identity's Zenoh config",
        description="fleet CA, one certificate per identity, and each identity's Zenoh config",
    )
    sp.add_argument(
        "--dir", default=str(DEFAULT_DIR), help=f"where they go (default {DEFAULT_DIR}; mode 0700)"
    )
    sp.add_argument(
        "--names",
        nargs="+",
        required=True,
        metavar="NAME",
        help="identities: router (any name but gcs-<id> / vehicle-<id>), gcs-<id>, vehicle-<id>",
    )
    sc = sub.add_parser(
        "certs",
        help="fleet CA and one certificate per identity, no configs",
        description="fleet CA and one certificate per identity, no configs",
    )
    sc.add_argument("dir", metavar="OUTDIR", help="where they go (created 0700)")
    sc.add_argument("names", nargs="+", metavar="NAME", help="identities (certificate CNs)")
    for s in (sp, sc):
        s.add_argument(
            "--hosts",
            type=comma_list,
            default=(),
            help="extra DNS names or IP addresses the certificates name, comma-separated "
            "(always: localhost, 127.0.0.1, ::1)",
        )
        s.add_argument(
            "--days", type=int, default=30, help="validity of new certificates (default 30)"
        )
    return p


def tls_cli(argv: list[str]) -> int:
    p = tls_parser()
    args = p.parse_args(argv)
    try:
        cfg = TlsConfig(
            directory=args.dir,
            names=tuple(args.names),
            hosts=tuple(args.hosts),
            days=args.days,
            configs=args.verb == "init",
        )
        written = init(cfg)
    except TlsSetupError as exc:
        die(p, str(exc))
    except OSError as exc:
        die(p, f"{getattr(exc, 'filename', None) or args.dir}: {exc.strerror or exc}")
    d = written[0].parent
    print(
        f"fleet CA {d / 'ca.pem'} (ca.key mode 0600: keep it with the operator); "
        f"certificate + key (0600) for {', '.join(cfg.names)}"
    )
    if args.verb == "init":
        for path in written:
            name = path.name.removesuffix(".json5")
            use = (
                "--zenoh-config for covey router (or covey gcs --mesh-mode router)"
                if role_of(name) == "router"
                else "--zenoh-config with --mesh-mode client"
            )
            print(f"  {path}  {use}")
    return 0
