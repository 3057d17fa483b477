"""The synthetic world as a video source (``synth:frames=200,seed=0,...``): the demo and the tests use it."""
from __future__ import annotations

from typing import Iterator

from ..common.errors import SourceError
from ..synth import SynthConfig, SynthWorld
from .sources import SourceFrame

# option in the spec → (SynthConfig field, converter)
_OPTIONS = {
    "frames": ("n_frames", int),
    "seed": ("seed", int),
    "width": ("width", int),
    "height": ("height", int),
    "person": ("person", bool),
    "chair": ("moved_chair", bool),
    "static": ("camera", lambda v: "static" if v else "orbit"),
}


class SynthSource:
    """Renders frames on the fly; ``depth=1`` also sends the exact depth as if from a depth sensor."""

    live = False

    def __init__(self, depth: int = 0, **options: int):
        unknown = sorted(set(options) - set(_OPTIONS))
        if unknown:
            raise SourceError(f"unknown synthetic source option(s) {unknown}; known: depth, {', '.join(_OPTIONS)}")
        fields = {_OPTIONS[k][0]: _OPTIONS[k][1](v) for k, v in options.items()}
        self.world = SynthWorld(SynthConfig(**fields))
        self.fps = self.world.config.fps
        self.name = "synth:" + ",".join(f"{k}={v}" for k, v in sorted(options.items()))
        self.with_depth = bool(depth)

    def frames(self) -> Iterator[SourceFrame]:
        for i in range(len(self.world)):
            frame = self.world.render(i)
            yield SourceFrame(i, int(frame.t_ns), frame.rgb, frame.depth if self.with_depth else None)
