"""``python -m services.features`` / ``kmvipe service features``: settings from KMVIPE_FEATURES_* and KMVIPE_BUS_*."""
from __future__ import annotations

import sys

from ..common.bus import Bus
from ..common.config import BusSettings
from ..common.errors import KmVipeError
from ..common.lifecycle import stop_on_signals, tune_malloc_for_frames
from ..common.logs import setup_logging
from .config import FeaturesSettings
from .service import build_state, run


def main(argv: list[str] | None = None) -> int:
    setup_logging("features")
    stop = stop_on_signals()
    tune_malloc_for_frames()
    cfg = FeaturesSettings()
    try:
        state = build_state(cfg)
        with Bus(BusSettings(), "features") as bus:
            run(cfg, bus, stop, state)
    except KmVipeError as exc:
        print(f"features: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
