"""``kmvipe bus certs`` and ``kmvipe bus users``: the secrets of the secured router and its edge access rules
(docs/SECURITY.md)."""
from __future__ import annotations

import argparse
from pathlib import Path

from . import keys

DEFAULT_OUT = "deploy/zenoh/secrets"
"""Where docker-compose.yml reads the secrets from (relative to the repository root)."""
DEFAULT_ROUTER_CONFIG = "deploy/zenoh/router.json5"
"""The router config docker-compose.yml and deploy/k8s run (relative to the repository root)."""


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

    p = sub.add_parser("users", help="add the service, gateway and edge credentials to the router's dictionary, "
                                     "and every edge credential's access rules to the router config")
    p.add_argument("--out", default=DEFAULT_OUT, help="output folder (default: %(default)s)")
    p.add_argument("--streams", nargs="*", default=[keys.DEFAULT_STREAM], metavar="STREAM",
                   help="one edge credential (edge-<stream>) per stream (default: %(default)s)")
    p.add_argument("--router-config", default=DEFAULT_ROUTER_CONFIG, type=Path, metavar="JSON5",
                   help="the router config whose edge rules are rewritten for every edge-<stream> of the dictionary "
                        "(default: %(default)s)")
    p.set_defaults(func=_cmd_users)


def _cmd_certs(args: argparse.Namespace) -> int:
    from .certs import DEFAULT_HOSTS, write_bus_certs  # cryptography loads only for this command

    paths = write_bus_certs(Path(args.out), tuple(args.hosts or DEFAULT_HOSTS), new_ca=args.new_ca)
    print(f"CA (give to every client, KMVIPE_BUS_TLS_ROOT_CA): {paths.ca_cert}")
    print(f"CA key (signs renewals; keep it off the router and the devices): {paths.ca_key}")
    print(f"router certificate and key: {paths.router_cert}, {paths.router_key}")
    return 0


def _cmd_users(args: argparse.Namespace) -> int:
    from .acl import edge_streams, read_router_config, render_router_config, write_router_config
    from .certs import USERS_FILE, write_bus_users

    streams = tuple(keys.check_name(s) for s in args.streams)
    render_router_config(read_router_config(args.router_config), streams)  # refused before any secret is written
    out = Path(args.out)
    written = write_bus_users(out, streams)
    for user, path in written.items():
        print(f"{user}: KMVIPE_BUS_USER={user} KMVIPE_BUS_PASSWORD_FILE={path}")
    print(f"router dictionary: {out / USERS_FILE}")
    edges = edge_streams(written)
    write_router_config(args.router_config, edges)
    print(f"router access rules: {args.router_config} (edge streams: {', '.join(edges) or 'none'}); restart the "
          "router to apply both")
    return 0
