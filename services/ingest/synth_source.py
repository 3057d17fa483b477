"""The synthetic world as a video source (``synth:frames=200,seed=0,...``): the demo and the tests use it."""
from __future__ import annotations

from typing import Iterator

from ..common.errors import ConfigError, SourceError
from ..synth import SynthWorld
from ..synth.spec import config_from_options
from .sources import SourceFrame


class SynthSource:
    """Renders frames on the fly; ``depth=1`` also sends the exact depth as if from a depth sensor."""

    live = False

    def __init__(self, depth: int = 0, **options: int):
        try:
            config = config_from_options(**options)
        except ConfigError as exc:
            raise SourceError(str(exc)) from exc
        self.world = SynthWorld(config)
        self.fps = self.world.config.fps
        self.name = "synth:" + ",".join(f"{k}={v}" for k, v in sorted(options.items()))
        self.with_depth = bool(depth)

    def frames(self) -> Iterator[SourceFrame]:
        for i in range(len(self.world)):
            frame = self.world.render(i)
            yield SourceFrame(i, int(frame.t_ns), frame.rgb, frame.depth if self.with_depth else None)
