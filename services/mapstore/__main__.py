"""``python -m services.mapstore``: settings from KMVIPE_MAPSTORE_* and KMVIPE_BUS_*.

With ``KMVIPE_MAPSTORE_STREAM=*`` (the default) it serves every stream a source announces, one map database each
(``db_path``'s ``{stream}``)."""

from __future__ import annotations

import sys

from services.common.lifecycle import tune_malloc_for_frames
from services.common.service_main import service_main
from services.common.streams import serve
from services.mapstore.config import MapstoreSettings
from services.mapstore.service import run
from services.mapstore.sessions import unfinished


def _body(bus, stop) -> None:
    cfg = MapstoreSettings()
    serve(cfg.stream, bus, stop,
          lambda stream, stream_bus, stream_stop: run(cfg.model_copy(update={"stream": stream}), stream_bus,
                                                      stream_stop).close(),
          keep_finished=True,  # a finished camera's map still answers queries, until a new one needs its place
          resume=lambda: unfinished(cfg.db_path))  # streams a killed mapstore left unfinished


def main(argv: list[str] | None = None) -> int:
    return service_main("mapstore", _body, tune_malloc_for_frames, blas_threads=1)


if __name__ == "__main__":
    sys.exit(main())
