"""``python -m services.ba`` / ``kmvipe service ba``: settings from KMVIPE_BA_* and KMVIPE_BUS_*.

With ``KMVIPE_BA_STREAM=*`` (the default) it serves every stream a source announces, each with its own state."""
from __future__ import annotations

import sys

from services.common.lifecycle import tune_malloc_for_tensors
from services.common.service_main import service_main
from services.common.streams import serve


def _body(bus, stop) -> None:
    # imported here, not at the top: service_main puts ba on TCMalloc first, by executing the process again, and
    # torch (~2 s) would have been imported for nothing
    from services.ba.checkpoint import pending
    from services.ba.service import build_state, run
    from services.ba.settings import BaSettings
    from services.ba.tracking_process import discard_spare, prewarm

    cfg = BaSettings()
    if cfg.tracking_process:  # its torch import overlaps with waiting for the first stream
        prewarm(cfg.tracker_factory(), cfg.tracking_nice)

    def one(stream, stream_bus, stream_stop):
        settings = cfg.model_copy(update={"stream": stream})
        run(settings, stream_bus, stream_stop, build_state(settings))

    try:
        serve(cfg.stream, bus, stop, one, resume=lambda: pending(cfg.checkpoint_dir))  # streams killed mid-way
    finally:
        discard_spare()  # stopped before a stream took it


def main(argv: list[str] | None = None) -> int:
    return service_main("ba", _body, tune_malloc_for_tensors)


if __name__ == "__main__":
    sys.exit(main())
