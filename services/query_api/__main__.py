"""``python -m services.query_api`` / ``kmvipe service query_api``: settings from KMVIPE_QUERY_* and KMVIPE_BUS_*."""
from __future__ import annotations

import sys

from ..common.bus import Bus
from ..common.config import BusSettings
from ..common.errors import KmVipeError
from ..common.lifecycle import stop_on_signals
from ..common.logs import setup_logging
from .config import QuerySettings
from .service import run


def main(argv: list[str] | None = None) -> int:
    setup_logging("query_api")
    stop = stop_on_signals()
    try:
        cfg = QuerySettings()
        with Bus(BusSettings(), "query_api") as bus:
            run(cfg, bus, stop)
    except KmVipeError as exc:
        print(f"query_api: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
