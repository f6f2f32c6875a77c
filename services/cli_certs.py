"""``lrsensor certs``: generate a fleet's secure profile (CA, TLS certificates, zenoh configs with access control).

Example::

    lrsensor certs --out secure --fleet reef --robots rov1,rov2 --hosts 192.168.2.1,shore.local \\
        --config-dir /etc/lrsensor/secure

writes ``secure/ca`` (keep ``ca-key.pem`` offline), ``secure/base`` (router config + base certificate),
``secure/rov1``, ``secure/rov2`` (client configs + robot certificates) and ``secure/operator``. Copy each
deployment folder to ``--config-dir`` on its machine and run ``lrsensor base --config .../base/base.json5`` and
``lrsensor rov --config .../rov1/rov1.json5``. See ``deploy/secure/README.md``.
"""

from __future__ import annotations

import argparse


def _csv(text: str) -> list[str]:
    return [part.strip() for part in text.split(",") if part.strip()]


def configure(parser: argparse.ArgumentParser) -> None:
    """Add the flags of this sub-command."""
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder (created)")
    parser.add_argument("--fleet", required=True, help="fleet name")
    parser.add_argument(
        "--robots", required=True, type=_csv, metavar="R1,R2", help="robot names (certificate common names)"
    )
    parser.add_argument(
        "--hosts",
        type=_csv,
        default=[],
        metavar="H1,H2",
        help="IP addresses or DNS names of the base station (added to its certificate next to 127.0.0.1, "
        "localhost); the first is what the robots connect to",
    )
    parser.add_argument("--prefix", default="lrs", help="key prefix (default lrs)")
    parser.add_argument(
        "--listen",
        action="append",
        metavar="ENDPOINT",
        help="base-station TLS endpoint (repeatable; default tls/0.0.0.0:7447)",
    )
    parser.add_argument(
        "--connect",
        action="append",
        metavar="ENDPOINT",
        help="endpoint the robots connect to (repeatable; default tls/<first host or 127.0.0.1>:<listen port>)",
    )
    parser.add_argument(
        "--config-dir",
        metavar="DIR",
        help="where the deployment folders will live on their machines (paths inside the JSON5 files); "
        "default: the output folder",
    )
    parser.add_argument("--days", type=int, default=825, help="validity of the issued certificates, days")
    parser.add_argument("--no-operator", action="store_true", help="do not issue the read-only operator certificate")
    parser.add_argument(
        "--new-ca", action="store_true", help="make a new CA even if OUT/ca holds one (default: reuse it)"
    )


def run(args: argparse.Namespace) -> int:
    """Generate the certificates and configs; print what was written. Returns the exit code."""
    from .certs import DEFAULT_BASE_LISTEN, generate_fleet

    secrets = generate_fleet(
        args.out,
        args.fleet,
        args.robots,
        hosts=args.hosts,
        prefix=args.prefix,
        listen=args.listen or [DEFAULT_BASE_LISTEN],
        connect=args.connect,
        config_dir=args.config_dir,
        operator=not args.no_operator,
        days=args.days,
        reuse_ca=not args.new_ca,
    )
    print(f"secure profile of fleet {args.fleet!r} written to {secrets.out_dir}")
    print()
    print("| deployment | certificate (CN) | config |")
    print("| --- | --- | --- |")
    print(f"| ca | {secrets.ca_cert} | (keep {secrets.ca_key.name} offline) |")
    idents = [("base", secrets.base), *secrets.robots.items()]
    if secrets.operator is not None:
        idents.append(("operator", secrets.operator))
    for name, ident in idents:
        print(f"| {name} | {ident.cert} ({ident.name}) | {secrets.configs[name]} |")
    return 0
