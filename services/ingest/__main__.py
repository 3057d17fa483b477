"""``python -m services.ingest`` / ``kmvipe service ingest``: settings from KMVIPE_INGEST_* and KMVIPE_BUS_*."""
from __future__ import annotations

import sys

from ..common.lifecycle import tune_malloc_for_frames
from ..common.service_main import service_main
from .config import IngestSettings
from .service import run


def _body(bus, stop) -> int:
    counters = run(IngestSettings(), bus, stop)
    return 0 if counters.sent or not counters.read else 1  # frames read but none delivered: say so


def main(argv: list[str] | None = None) -> int:
    return service_main("ingest", _body, tune_malloc_for_frames)


if __name__ == "__main__":
    sys.exit(main())
