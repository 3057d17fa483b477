"""``python -m services.mapstore``: settings from KMVIPE_MAPSTORE_* and KMVIPE_BUS_*."""

from __future__ import annotations

import sys

from services.common.bus import Bus
from services.common.config import BusSettings
from services.common.errors import KmVipeError
from services.common.lifecycle import stop_on_signals, tune_malloc_for_frames
from services.common.logs import setup_logging
from services.mapstore.config import MapstoreSettings
from services.mapstore.service import run


def main(argv: list[str] | None = None) -> int:
    setup_logging("mapstore")
    stop = stop_on_signals()
    tune_malloc_for_frames()
    cfg = MapstoreSettings()
    try:
        with Bus(BusSettings(), "mapstore") as bus:
            run(cfg, bus, stop).close()
    except KmVipeError as exc:
        print(f"mapstore: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
