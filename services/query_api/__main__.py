"""``python -m services.query_api`` / ``kmvipe service query_api``: settings from KMVIPE_QUERY_* and KMVIPE_BUS_*."""
from __future__ import annotations

import sys

from ..common.service_main import service_main
from .config import QuerySettings
from .service import run


def main(argv: list[str] | None = None) -> int:
    return service_main("query_api", lambda bus, stop: run(QuerySettings(), bus, stop))


if __name__ == "__main__":
    sys.exit(main())
