"""The tracking thread of the ba service: every frame (and keyframe) posed on arrival, published at once.

It has its own inbox, so a frame never waits behind a keyframe's window BA; the mapping loop hands it a new
reference keyframe after each BA (:meth:`TrackingLoop.set_reference`). The tracker itself runs in a process of
its own (:class:`~services.ba.tracking_process.TrackerProcess`, ``BaSettings.tracking_process``): this thread only
moves frames to it and poses back. Poses it publishes carry ``tracked=True``: consumers keep them until mapping
publishes a revision of the same frame.
"""
from __future__ import annotations

import logging
import threading
import time
from collections import deque
from typing import NamedTuple

import numpy as np
import torch

from services.common import keys
from services.common.bus import Bus, Inbox
from services.common.lifecycle import nice_this_thread
from services.common.rotations import is_rigid
from services.common.schema import Eos, FrameLite, Keyframe, Poses
from services.ba.frontend.tracker import Reference
from services.ba.tracking_process import LocalTracker, TrackerProcess

log = logging.getLogger(__name__)
POLL_S = 0.05
STARTUP_BACKLOG = 512  # frames held, not dropped, while the tracker starts (a spawned process: seconds)


class Anchor(NamedTuple):
    """Where tracking put a frame, for mapping: anchored there instead of aligned again, solved again with
    ``flow`` once the keyframe is refined, and a keyframe's start."""

    ref_seq: int  # the reference keyframe
    ref_from_cam: torch.Tensor  # (4, 4) float64
    world_from_cam: torch.Tensor  # (4, 4) float64
    flow: tuple[torch.Tensor, torch.Tensor] | None = None  # tracking's (h, w, 2) grid targets and (h, w) confidence


class TrackingLoop:
    """Runs a tracker on a thread over ``inbox`` (frame_lite and keyframe messages of one stream)."""

    def __init__(self, tracker: LocalTracker | TrackerProcess, bus: Bus, inbox: Inbox, stream: str,
                 anchors: dict[int, Anchor], niceness: int = 0):
        self.tracker, self.bus, self.inbox, self.stream, self.niceness = tracker, bus, inbox, stream, niceness
        self._lock = threading.Lock()
        self._pending_ref: Reference | None = None
        self._reset = False
        self.tracked = 0  # frames posed by tracking in this stream
        self.not_rigid = 0  # tracked poses that were not rigid transforms (not published)
        self.refused = 0  # tracked poses beyond mapping's speed, the prediction published instead (this stream)
        self.last_seq = -1  # highest seq handled (for progress reports)
        # seq -> Anchor (dict operations are atomic; mapping pops what it uses, reset clears the rest)
        self.anchors = anchors
        self._skipped: deque[FrameLite | Keyframe] = deque()  # frames the inbox dropped: predicted poses only
        inbox.on_drop = lambda delivery: self._skipped.append(delivery.msg)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"stream-{stream}/tracking", daemon=True)

    def start(self) -> None:
        self._thread.start()

    @property
    def in_process(self) -> bool:
        """Whether the tracker runs in a process of its own (False: on this thread, in mapping's interpreter, as
        configured or because its process did not start)."""
        return isinstance(self.tracker, TrackerProcess)

    def _start_tracker(self) -> None:
        """On the tracking thread, so mapping's loop (its progress reports, a resumed stream's catch-up) never
        waits for it: a tracking process that was not started ahead (``prewarm``), or one that comes up slowly on
        a loaded CPU, takes a second or more to import numpy, OpenCV and the tracker. Frames meanwhile queue in the inbox beyond its real-time bound:
        dropped, a frame before the map would get no pose at all (there is nothing to predict from), and tracking
        catches up in a fraction of the wait (a frame before the map costs a few milliseconds). The inbox returns
        to its bound once tracking has caught up (:meth:`Inbox.widen`)."""
        self.inbox.widen(STARTUP_BACKLOG)
        began = time.monotonic()
        try:
            self.tracker.start()
        except RuntimeError as exc:  # tracking on a thread of ba is slower, not wrong
            log.error("tracking process did not start; tracking on a thread of ba instead",
                      extra={"stream": self.stream, "error": str(exc)})
            self.tracker = LocalTracker(self.tracker.make_tracker)
        log.info("tracking started", extra={"stream": self.stream, "in_process": self.in_process,
                                            "seconds": round(time.monotonic() - began, 2),
                                            "queued": self.inbox.qsize()})

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self.tracker.close()

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
        self._start_tracker()
        while not self._stop.is_set():
            delivery = self.inbox.get(POLL_S)
            try:
                self._take_news()
                while self._skipped:  # frames tracking had no time for still get a pose now, by prediction
                    self._predicted(self._skipped.popleft())
                if delivery is None or isinstance(delivery.msg, Eos):
                    continue
                self._track(delivery.msg)
            except (ValueError, RuntimeError) as exc:  # one bad frame, or a lost tracking process, never stops it
                seq = None if delivery is None else delivery.msg.seq
                log.warning("frame not tracked", extra={"stream": self.stream, "seq": seq, "error": str(exc)})

    def _take_news(self) -> None:
        """A reset or a new reference from mapping, if one came."""
        with self._lock:
            reset, self._reset = self._reset, False
            ref, self._pending_ref = self._pending_ref, None
        if reset:
            self.tracker.reset()
            self.tracked = self.refused = 0
            self.anchors.clear()
        if ref is not None:
            self.tracker.set_reference(ref)

    def _predicted(self, msg: FrameLite | Keyframe) -> None:
        pose = self.tracker.predict(msg.t_ns)  # None before the map
        if pose is not None:
            self._publish(msg, pose)

    def _publish(self, msg: FrameLite | Keyframe, pose: np.ndarray, provisional: bool = False) -> None:
        if not is_rigid(pose):  # the frame gets mapping's pose later; this one has no quaternion
            self.not_rigid += 1
            log.warning("tracked pose is not a rigid transform; not published",
                        extra={"stream": self.stream, "seq": msg.seq, "count": self.not_rigid})
            return
        self.bus.publish(keys.topic(self.stream, keys.POSE), Poses(
            self.stream, msg.seq, time.time_ns(), frame_seqs=np.array([msg.seq], np.int64),
            stamps_ns=np.array([msg.t_ns], np.int64), poses=np.asarray(pose, np.float64)[None],
            tracked=True, provisional=provisional))

    def _track(self, msg: FrameLite | Keyframe) -> None:
        self.last_seq = max(self.last_seq, msg.seq)
        began = time.monotonic()
        out = self.tracker.step(isinstance(msg, Keyframe), msg.seq, msg.t_ns, msg.image, msg.intrinsics)
        log.debug("frame tracked", extra={"stream": self.stream, "seq": msg.seq, "queued": self.inbox.qsize(),
                                          "seconds": round(time.monotonic() - began, 3)})
        if out is None:
            return
        self.tracked += 1
        if out.ok:
            flow = None if out.flow is None else tuple(torch.from_numpy(a) for a in out.flow)
            self.anchors[msg.seq] = Anchor(out.ref_seq, torch.from_numpy(out.ref_from_cam), torch.from_numpy(out.pose),
                                           flow)
        self._publish(msg, out.pose, provisional=out.ref_seq < 0)
        if out.refused:
            self.refused += 1
            log.info("frame kept its predicted pose (the pose tracked lay beyond mapping's speed)",
                     extra={"stream": self.stream, "seq": msg.seq, "count": self.refused})
        elif not out.ok and out.ref_seq >= 0:
            log.info("frame kept its predicted pose (weak flow)", extra={"stream": self.stream, "seq": msg.seq})
