"""``python -m services.ingest`` / ``kmvipe service ingest``: settings from KMVIPE_INGEST_* and KMVIPE_BUS_*."""
from __future__ import annotations

import sys

from ..common.bus import Bus
from ..common.config import BusSettings
from ..common.errors import KmVipeError
from ..common.lifecycle import stop_on_signals, tune_malloc_for_frames
from ..common.logs import setup_logging
from .config import IngestSettings
from .service import run


def main(argv: list[str] | None = None) -> int:
    setup_logging("ingest")
    stop = stop_on_signals()
    tune_malloc_for_frames()
    cfg = IngestSettings()
    try:
        with Bus(BusSettings(), "ingest") as bus:
            counters = run(cfg, bus, stop)
    except KmVipeError as exc:
        print(f"ingest: {exc}", file=sys.stderr)
        return 2
    return 0 if counters.sent or not counters.read else 1


if __name__ == "__main__":
    sys.exit(main())
