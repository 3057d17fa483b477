"""What ingest sent that features has not taken yet, sent again when a features instance restarts.

features reports, with its credit, the highest frame seq it has handled (``durable``: what it handled went on to
ba and the mapstore, which keep it; a features process keeps nothing itself). A lossless source keeps the frames
it sent after that point — at most the credit window plus what features may be ahead of ba, a few dozen — and its
end of stream. When a features consumer it has not heard from reports after another one did (a features killed
and restarted: its worker has a new name per start), the source publishes them again in order, and it keeps its
stream announced after its own end of stream until features has sent its end of stream, so a features that
restarts after the last frame still finds the stream and gets what it missed."""
from __future__ import annotations

import dataclasses
import threading
from collections import deque

from ..common.restarts import Restarts
from ..common.schema import Credit, Eos, Frame

PREFIX = "features-"


class ResendBuffer:
    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._frames: deque[Frame] = deque()
        self._eos: Eos | None = None
        self._last: Frame | None = None  # the newest frame sent
        self._restarts = Restarts(PREFIX)
        self._pending = False
        self.durable = -1
        # frames are kept only once a features instance reports what it handled: only it asks for them again, and
        # without its reports nothing would ever trim them (a stream to another consumer kept every frame)
        self._watched = False

    def on_credit(self, msg: Credit) -> None:
        """A credit message (Zenoh thread)."""
        if not msg.consumer.startswith(PREFIX) or not msg.checkpoints:
            return
        restarted = bool(self._restarts.replaced_by(msg.consumer))  # it lost what was in flight to its predecessor
        with self._lock:
            self._watched = True
            self._pending = self._pending or restarted
            # what any features instance handled went on downstream: a restarted one needs only what came after
            self.durable = max(self.durable, msg.durable)
            self._trim()

    def record(self, msg: Frame | Eos) -> None:
        """A frame or the end of stream this source published (loop thread)."""
        with self._lock:
            if isinstance(msg, Eos):
                self._eos = msg
                return
            self._last = msg
            if self._watched:
                self._frames.append(msg)
            self._trim()

    def _trim(self) -> None:
        while self._frames and self._frames[0].seq <= self.durable:
            self._frames.popleft()

    def due(self) -> list[Frame | Eos]:
        """What to publish again now (loop thread): after a features restart, every frame it has not handled."""
        with self._lock:
            if not self._pending:
                return []
            self._pending = False
            # stamped with what is handled now: the new instance counts as lost only what came after it
            out: list[Frame | Eos] = [dataclasses.replace(f, features_handled=self.durable)
                                      for f in self._frames if f.seq > self.durable]
            if not out and self._last is not None:
                # its predecessor had handled everything: the newest frame again tells the new one where the
                # stream is (its credit counts from the frames it has seen; the repeat is not taken twice downstream)
                out.append(dataclasses.replace(self._last, features_handled=self.durable))
            if self._eos is not None:
                out.append(self._eos)
        return out
