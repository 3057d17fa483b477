"""``python -m services.features`` / ``kmvipe service features``: settings from KMVIPE_FEATURES_* and KMVIPE_BUS_*."""
from __future__ import annotations

import sys

from ..common.service_main import service_main
from .config import FeaturesSettings
from .service import build_state, run


def _body(bus, stop) -> None:
    cfg = FeaturesSettings()
    run(cfg, bus, stop, build_state(cfg))


def main(argv: list[str] | None = None) -> int:
    return service_main("features", _body, handles_frames=True)


if __name__ == "__main__":
    sys.exit(main())
