"""``python -m services.features`` / ``kmvipe service features``: settings from KMVIPE_FEATURES_* and KMVIPE_BUS_*.

With ``KMVIPE_FEATURES_STREAM=*`` (the default) it serves every stream a source announces, the models loaded once."""
from __future__ import annotations

import sys

from ..common.lifecycle import tune_malloc_for_frames
from ..common.service_main import service_main
from ..common.streams import serve
from .config import FeaturesSettings
from .service import build_state, load_models, run


def _body(bus, stop) -> None:
    cfg = FeaturesSettings()
    models = load_models(cfg)

    def one(stream, stream_bus, stream_stop):
        settings = cfg.model_copy(update={"stream": stream})
        run(settings, stream_bus, stream_stop, build_state(settings, models))

    serve(cfg.stream, bus, stop, one)


def main(argv: list[str] | None = None) -> int:
    # the PCA's matmuls are numpy's since features runs without torch: one BLAS thread, as the mapstore, so that an
    # idle pool's spinning threads take no CPU from tracking and mapping (KITTI keyframes: 417 ms described and
    # coded with one thread, 442 with two)
    return service_main("features", _body, tune_malloc_for_frames, blas_threads=1)


if __name__ == "__main__":
    sys.exit(main())
