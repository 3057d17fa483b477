"""``kmvipe bus certs`` and ``kmvipe bus users``: the secrets of the secured router (docs/SECURITY.md)."""
from __future__ import annotations

import argparse
from pathlib import Path

from . import keys

DEFAULT_OUT = "deploy/zenoh/secrets"
"""Where docker-compose.yml reads the secrets from (relative to the repository root)."""


def register(subparsers) -> None:
    bus = subparsers.add_parser("bus", help="secrets of the secured Zenoh router (TLS certificates, credentials)")
    sub = bus.add_subparsers(dest="bus_command", required=True)

    p = sub.add_parser("certs", help="make the router's TLS certificate (and the private CA that signs it, if absent)")
    p.add_argument("--out", default=DEFAULT_OUT, help="output folder (default: %(default)s)")
    p.add_argument("--hosts", nargs="+", metavar="HOST",
                   help="names and addresses clients dial the router by (default: zenoh localhost 127.0.0.1); "
                        "add the host's LAN name or address for edge devices")
    p.add_argument("--new-ca", action="store_true",
                   help="replace the CA too (every client must then get the new ca.pem); default: keep it")
    p.set_defaults(func=_cmd_certs)

    p = sub.add_parser("users", help="add the service, gateway and edge credentials to the router's dictionary")
    p.add_argument("--out", default=DEFAULT_OUT, help="output folder (default: %(default)s)")
    p.add_argument("--streams", nargs="*", default=[keys.DEFAULT_STREAM], metavar="STREAM",
                   help="one edge credential (edge-<stream>) per stream (default: %(default)s)")
    p.set_defaults(func=_cmd_users)


def _cmd_certs(args: argparse.Namespace) -> int:
    from .certs import DEFAULT_HOSTS, write_bus_certs  # cryptography loads only for this command

    paths = write_bus_certs(Path(args.out), tuple(args.hosts or DEFAULT_HOSTS), new_ca=args.new_ca)
    print(f"CA (give to every client, KMVIPE_BUS_TLS_ROOT_CA): {paths.ca_cert}")
    print(f"CA key (signs renewals; keep it off the router and the devices): {paths.ca_key}")
    print(f"router certificate and key: {paths.router_cert}, {paths.router_key}")
    return 0


def _cmd_users(args: argparse.Namespace) -> int:
    from .certs import USERS_FILE, write_bus_users

    streams = tuple(keys.check_name(s) for s in args.streams)
    out = Path(args.out)
    for user, path in write_bus_users(out, streams).items():
        print(f"{user}: KMVIPE_BUS_USER={user} KMVIPE_BUS_PASSWORD_FILE={path}")
    print(f"router dictionary: {out / USERS_FILE} (an edge-<stream> user also needs its rules in "
          "deploy/zenoh/router.json5)")
    return 0
