"""The semantics thread of the features service: DINO features and PCA codes of keyframes, off the frame path.

Keyframe geometry leaves the service at once; this thread describes keyframes with the backbone (about a second
each on two CPU cores) and hands back codes for the loop to publish. Lossless streams get codes for every
keyframe, in order; a real-time stream's backbone takes the newest waiting keyframe and skips the stale ones
(counted), since a live camera's map is better served by fresh semantics than by a queue that never empties.
The thread runs at a lower priority than the frame path (``semantics_nice``); :func:`load_at_niceness` loads
the backbone on a thread of that priority too, so the runtime's worker threads (onnxruntime's pool) inherit it.

Before :meth:`SemanticsWorker.start`, :meth:`~SemanticsWorker.submit` describes inline: the handlers are then
plain functions (tests drive them that way).
"""
from __future__ import annotations

import logging
import threading
from collections import deque
from typing import Callable

from services.common.lifecycle import nice_this_thread

from .core.pca import PcaBasis as CoreBasis
from .core.pipeline import CodeQueue, FeaturesCore, KeyframeOut

log = logging.getLogger(__name__)

Coded = tuple[CoreBasis | None, list]  # (new basis or None, [(KeyframeOut, codes)]) as CodeQueue returns it
_FLUSH = object()


class SemanticsWorker:
    """Describes and codes keyframes on its own thread; results come back through :meth:`take`."""

    def __init__(self, core: FeaturesCore, codes: CodeQueue, niceness: int = 0, stream: str = ""):
        self.core, self.codes, self.niceness = core, codes, niceness
        self._pending: deque = deque()
        self._results: deque[Coded] = deque()
        self._cond = threading.Condition()
        self._busy = False
        self._stop = False
        self.skipped = 0  # real-time keyframes the backbone never described
        name = f"stream-{stream}/semantics" if stream else "semantics"  # the stream's name in its log lines
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        with self._cond:
            self._stop = True
            self._cond.notify_all()
        self._thread.join(timeout=10)

    def submit(self, kf: KeyframeOut, realtime: bool) -> None:
        if not self._thread.is_alive():
            self._results.append(self.codes.add(self._describe(kf)))
            return
        with self._cond:
            if realtime:  # only the newest waiting keyframe is worth the backbone's time
                stale = [p for p in self._pending if p is not _FLUSH]
                self.skipped += len(stale)
                self._pending = deque(p for p in self._pending if p is _FLUSH)
            self._pending.append(kf)
            self._cond.notify_all()

    def flush(self) -> None:
        """End of stream: after what is queued, fit the basis on what there is and code every held keyframe."""
        if not self._thread.is_alive():
            self._results.append(self.codes.flush())
            return
        with self._cond:
            self._pending.append(_FLUSH)
            self._cond.notify_all()

    def backlog(self) -> int:
        """Keyframes waiting or being described."""
        with self._cond:
            return sum(p is not _FLUSH for p in self._pending) + int(self._busy)

    def idle(self) -> bool:
        with self._cond:
            return not self._pending and not self._busy

    def take(self) -> list[Coded]:
        """Results since the last call, in order (a new basis always comes with or before the codes it made)."""
        with self._cond:
            out, self._results = [r for r in self._results if r[0] is not None or r[1]], deque()
            return out

    def _run(self) -> None:
        nice_this_thread(self.niceness)
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._pending or self._stop)
                if self._stop:
                    return
                item, self._busy = self._pending.popleft(), True
            try:
                result = self.codes.flush() if item is _FLUSH else self.codes.add(self._describe(item))
            except (ValueError, RuntimeError):  # one keyframe's failure must not stop semantics
                log.exception("keyframe not described", extra={"seq": getattr(item, "seq", -1)})
                result = (None, [])
            with self._cond:
                self._busy = False
                self._results.append(result)

    def _describe(self, kf: KeyframeOut) -> KeyframeOut:
        set_frame = getattr(self.core.backbone, "set_frame", None)  # the synthetic oracle needs the frame
        if set_frame is not None:
            set_frame(kf.seq)
        return self.core.describe(kf)


def load_at_niceness(load: Callable[[], object], niceness: int) -> object:
    """``load()`` on a thread of the given niceness; its result, or its exception re-raised here."""
    box: dict[str, object] = {}

    def body() -> None:
        nice_this_thread(niceness)
        try:
            box["value"] = load()
        except BaseException as exc:  # re-raised in the caller's thread
            box["error"] = exc

    thread = threading.Thread(target=body, name="load-backbone")
    thread.start()
    thread.join()
    if "error" in box:
        raise box["error"]
    return box["value"]
