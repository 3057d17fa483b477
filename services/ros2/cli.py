"""``kmvipe ros2 bridge``: publish a stream's poses, map and intrinsics to ROS 2; ``kmvipe ros2 keys``: print the
Zenoh key expressions that carries them on."""
from __future__ import annotations

import argparse
import json
import os
import sys

from ..common.keys import DEFAULT_STREAM
from .core.names import FORMS

# option -> (environment variable, how to write the value)
_BRIDGE_OPTIONS = {
    "stream": ("KMVIPE_ROS2_STREAM", str),
    "form": ("KMVIPE_ROS2_FORM", str),
    "domain_id": ("KMVIPE_ROS2_DOMAIN_ID", str),
    "distro": ("KMVIPE_ROS2_DISTRO", str),
    "axes": ("KMVIPE_ROS2_AXES", str),
    "map_period": ("KMVIPE_ROS2_MAP_PERIOD_S", str),
    "ros_connect": ("KMVIPE_ROS2_ZENOH_CONNECT", json.dumps),
}


def _add_common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--stream", help=f"KM-ViPE stream to publish (default {DEFAULT_STREAM})")
    p.add_argument("--form", choices=FORMS, help="rmw_zenoh: ROS 2 nodes on rmw_zenoh_cpp (default); bridge: "
                                                 "behind zenoh-bridge-ros2dds")
    p.add_argument("--domain-id", type=int, help="ROS_DOMAIN_ID (rmw_zenoh form; default 0)")
    p.add_argument("--distro", choices=("jazzy", "kilted", "rolling", "humble"),
                   help="ROS 2 release of the rmw_zenoh nodes (humble: no type hashes; default jazzy)")


def register(subparsers) -> None:
    """Add ``ros2`` (sub-commands ``bridge`` and ``keys``) to a CLI's subparsers."""
    parser = subparsers.add_parser("ros2", help="ROS 2 over Zenoh: publish poses, path, map and camera info")
    sub = parser.add_subparsers(dest="ros2_command", required=True)
    bridge = sub.add_parser("bridge", help="publish a stream's TF, path, point cloud and camera info to ROS 2 "
                                           "(settings: KMVIPE_ROS2_*, KMVIPE_ROS2_ZENOH_*, KMVIPE_BUS_*)")
    _add_common(bridge)
    bridge.add_argument("--axes", choices=("flu", "optical"), help="map frame axes (default flu: z up)")
    bridge.add_argument("--map-period", type=float, metavar="S", help="point cloud refresh period, 0: none")
    bridge.add_argument("--connect", action="append", metavar="ENDPOINT",
                        help="the KM-ViPE bus's router (client mode), e.g. tcp/127.0.0.1:7447")
    bridge.add_argument("--ros-connect", action="append", metavar="ENDPOINT",
                        help="the ROS 2 Zenoh router (default tcp/127.0.0.1:7447: rmw_zenohd or "
                             "zenoh-bridge-ros2dds)")
    bridge.set_defaults(func=run_bridge)
    show = sub.add_parser("keys", help="print the topics, types and Zenoh key expressions the bridge uses")
    _add_common(show)
    show.set_defaults(func=run_keys)


def bridge_environment(args: argparse.Namespace) -> dict[str, str]:
    """The environment variables the options given stand for (the service reads its settings from there)."""
    env = {var: write(getattr(args, name)) for name, (var, write) in _BRIDGE_OPTIONS.items()
           if getattr(args, name, None) is not None}
    if getattr(args, "connect", None):
        env.update(KMVIPE_BUS_MODE="client", KMVIPE_BUS_CONNECT=json.dumps(args.connect), KMVIPE_BUS_LISTEN="[]")
    return env


def run_bridge(args: argparse.Namespace) -> int:
    from .__main__ import main as service

    os.environ.update(bridge_environment(args))
    return service()


def key_table(cfg) -> list[tuple[str, str, str]]:
    """``(topic, message type, key expression)`` of everything the bridge publishes."""
    from .core import messages
    from .core.names import topic_key

    topics = ((cfg.tf_topic, messages.TF), (cfg.path_topic, messages.PATH), (cfg.cloud_topic, messages.CLOUD),
              (cfg.camera_info_topic, messages.CAMERA_INFO))
    return [(topic, msgtype, topic_key(cfg.form, topic, msgtype, messages.type_hash(msgtype, cfg.distro),
                                       cfg.domain_id)) for topic, msgtype in topics]


def run_keys(args: argparse.Namespace) -> int:
    from .config import Ros2Settings

    given = {name: getattr(args, name) for name in ("stream", "form", "domain_id", "distro")
             if getattr(args, name) is not None}
    for topic, msgtype, key in key_table(Ros2Settings(**given)):
        print(f"{topic:<24} {msgtype:<28} {key}")
    return 0


def main(argv: list[str] | None = None) -> int:
    """Stand-alone entry point: ``python -m services.ros2.cli bridge ...``."""
    parser = argparse.ArgumentParser(prog="kmvipe-ros2")
    register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(["ros2", *(argv if argv is not None else sys.argv[1:])])
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
