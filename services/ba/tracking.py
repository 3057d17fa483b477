"""The tracking thread of the ba service: every frame (and keyframe) posed on arrival, published at once.

It has its own inbox, so a frame never waits behind a keyframe's window BA; the mapping loop hands it a new
reference keyframe after each BA (:meth:`TrackingLoop.set_reference`). Poses it publishes carry
``tracked=True``: consumers keep them until mapping publishes a revision of the same frame.
"""
from __future__ import annotations

import logging
import threading
import time
from collections import deque

import cv2
import numpy as np
import torch

from services.common import keys
from services.common.bus import Bus, Inbox
from services.common.lifecycle import nice_this_thread
from services.common.schema import Eos, FrameLite, Keyframe, Poses
from services.ba.core import se3
from services.ba.core.flow import to_grey
from services.ba.frontend.tracker import Reference, Tracker

log = logging.getLogger(__name__)
POLL_S = 0.05


class TrackingLoop:
    """Runs :class:`Tracker` on a thread over ``inbox`` (frame_lite and keyframe messages of one stream)."""

    def __init__(self, tracker: Tracker, bus: Bus, inbox: Inbox, stream: str,
                 anchors: dict[int, tuple[int, torch.Tensor, torch.Tensor]], niceness: int = 0):
        self.tracker, self.bus, self.inbox, self.stream, self.niceness = tracker, bus, inbox, stream, niceness
        self._lock = threading.Lock()
        self._pending_ref: Reference | None = None
        self._reset = False
        self.tracked = 0  # frames posed by tracking in this stream
        self.last_seq = -1  # highest seq handled (for progress reports)
        # seq -> (reference keyframe seq, (4, 4) reference_from_cam, (4, 4) world_from_cam): mapping anchors the
        # frame there instead of aligning it again, and starts a keyframe from it (dict operations are atomic;
        # mapping pops what it uses, reset clears the rest)
        self.anchors = anchors
        self._skipped: deque[FrameLite | Keyframe] = deque()  # frames the inbox dropped: predicted poses only
        inbox.on_drop = lambda delivery: self._skipped.append(delivery.msg)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"stream-{stream}/tracking", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)

    def set_reference(self, ref: Reference) -> None:
        """Called by the mapping loop: track against ``ref`` from the next frame on."""
        with self._lock:
            self._pending_ref = ref

    def reset(self) -> None:
        """End of stream: the next stream starts without a map."""
        with self._lock:
            self._pending_ref, self._reset = None, True

    def _run(self) -> None:
        nice_this_thread(self.niceness)
        while not self._stop.is_set():
            delivery = self.inbox.get(POLL_S)
            with self._lock:
                if self._reset:
                    self.tracker.reset()
                    self.tracked, self._reset = 0, False
                    self.anchors.clear()
                ref, self._pending_ref = self._pending_ref, None
            if ref is not None:
                self.tracker.set_reference(ref)
            while self._skipped:  # frames tracking had no time for still get a pose now, by prediction
                self._predicted(self._skipped.popleft())
            if delivery is None or isinstance(delivery.msg, Eos):
                continue
            try:
                self._track(delivery.msg)
            except (ValueError, RuntimeError) as exc:  # one bad frame never stops tracking
                log.warning("frame not tracked", extra={"stream": self.stream, "seq": delivery.msg.seq,
                                                        "error": str(exc)})

    def _predicted(self, msg: FrameLite | Keyframe) -> None:
        if self.tracker.reference is None:
            return
        self._publish(msg, self.tracker.predict(msg.t_ns))

    def _publish(self, msg: FrameLite | Keyframe, pose: torch.Tensor, provisional: bool = False) -> None:
        self.bus.publish(keys.topic(self.stream, keys.POSE), Poses(
            self.stream, msg.seq, time.time_ns(), frame_seqs=np.array([msg.seq], np.int64),
            stamps_ns=np.array([msg.t_ns], np.int64), poses=pose.detach().cpu().numpy().astype(np.float64)[None],
            tracked=True, provisional=provisional))

    def _track(self, msg: FrameLite | Keyframe) -> None:
        self.last_seq = max(self.last_seq, msg.seq)
        image, intrinsics = msg.image, msg.intrinsics
        if isinstance(msg, Keyframe):  # before the map, provisional poses run at the size frames arrive in
            image, intrinsics = half_size(to_grey(image), intrinsics)
        out = self.tracker.track(msg.seq, msg.t_ns, image, intrinsics)
        if out is None:
            return
        self.tracked += 1
        if isinstance(msg, Keyframe):
            self.tracker.keyframe_seen(msg.seq)
        if out.ok:
            self.anchors[msg.seq] = (out.ref_seq, se3.inverse(self.tracker.reference.pose) @ out.pose, out.pose)
            if isinstance(msg, Keyframe):  # tracking moves on to it now, whether or not mapping keeps up
                self.tracker.promote(msg.seq, msg.t_ns, to_grey(msg.image), out.pose)
        self._publish(msg, out.pose, provisional=out.ref_seq < 0)
        if not out.ok and out.ref_seq >= 0:
            log.info("frame kept its predicted pose (weak flow)", extra={"stream": self.stream, "seq": msg.seq})


def half_size(grey: np.ndarray, intrinsics: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A working-resolution grey image and its (4,) intrinsics at half size (the resize rule of
    docs/CONVENTIONS.md)."""
    h, w = grey.shape[:2]
    fx, fy, cx, cy = (float(v) for v in intrinsics)
    small = cv2.resize(grey, (w // 2, h // 2), interpolation=cv2.INTER_AREA)
    return small, np.array([fx / 2, fy / 2, (cx + 0.5) / 2 - 0.5, (cy + 0.5) / 2 - 0.5])
