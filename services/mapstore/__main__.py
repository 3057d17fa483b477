"""``python -m services.mapstore``: settings from KMVIPE_MAPSTORE_* and KMVIPE_BUS_*."""

from __future__ import annotations

import sys

from services.common.service_main import service_main
from services.mapstore.config import MapstoreSettings
from services.mapstore.service import run


def main(argv: list[str] | None = None) -> int:
    return service_main("mapstore", lambda bus, stop: run(MapstoreSettings(), bus, stop).close(), handles_frames=True,
                        blas_threads=1)


if __name__ == "__main__":
    sys.exit(main())
