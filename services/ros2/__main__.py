"""``python -m services.ros2`` / ``kmvipe ros2 bridge``: the ROS 2 bridge; settings from KMVIPE_ROS2_*,
KMVIPE_ROS2_ZENOH_* (the ROS side's Zenoh session) and KMVIPE_BUS_* (KM-ViPE's bus)."""
from __future__ import annotations

import sys

from ..common.service_main import service_main
from .bridge import run
from .config import Ros2Settings, RosZenohSettings
from .transport import RosNode


def _body(bus, stop) -> int:
    cfg = Ros2Settings()
    with RosNode(cfg, RosZenohSettings()) as node:
        run(cfg, bus, node, stop)
    return 0


def main(argv: list[str] | None = None) -> int:
    return service_main("ros2", _body)


if __name__ == "__main__":
    sys.exit(main())
