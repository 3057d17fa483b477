"""Frame-rate tracking in a process of its own, so that it never waits for mapping's interpreter.

Tracking and mapping in one process share one Python interpreter: a frame's motion-only alignment takes the
interpreter hundreds of times, and each time waits behind mapping's BA. On a 2-core CPU that capped ba at one
core and put a live frame's pose hundreds of milliseconds behind its capture. Here the :class:`Tracker` lives in
a child process (``spawn``: the parent holds Zenoh's threads, which a fork would copy half-alive); ba's tracking
thread sends it each frame and publishes the pose it gets back. Only numpy arrays cross the pipe. The child never
imports torch (the tracker is numpy and OpenCV): torch would add ~200 MB to it and seconds to its start.

A child that dies (killed, out of memory) is started again with the last reference mapping gave it: the frame
in hand is tracked by the new child, nothing waits forever (``timeout_s``), and the restarts are counted.
"""
from __future__ import annotations

import functools
import logging
import multiprocessing as mp
import os
import threading
from typing import Callable, NamedTuple

import cv2
import numpy as np

from services.ba.core import se3_numpy as se3
from services.ba.core.flow import to_grey
from services.ba.frontend.tracker import Reference, Tracker
from services.common.camera import scale_intrinsics
from services.common.lifecycle import limit_blas_threads

log = logging.getLogger(__name__)


class Step(NamedTuple):
    """One frame's tracking result, as plain arrays."""

    pose: np.ndarray  # (4, 4) float64 world_from_cam
    ok: bool  # aligned (False: the constant-velocity prediction, or a provisional rotation before the map)
    ref_seq: int  # the keyframe it was aligned to (-1: before the map, provisional)
    ref_from_cam: np.ndarray | None  # (4, 4) float64 relative to that keyframe, when ``ok``
    flow: tuple[np.ndarray, np.ndarray] | None = None  # tracking's flow from that keyframe, when ``ok``: (h, w, 2)
    # float32 grid targets, (h, w) float32 confidence (mapping solves the frame again with it, frames.py)
    refused: bool = False  # the pose tracking found lay beyond mapping's speed: ``pose`` is the prediction


def step(tracker: Tracker, is_keyframe: bool, seq: int, t_ns: int, image: np.ndarray,
         intrinsics: np.ndarray) -> Step | None:
    """Track one frame (a keyframe moves tracking on to it); None before the map when nothing can be said."""
    if is_keyframe:  # tracked at the size frames arrive in; its working-size image may become the reference
        grey = to_grey(image)
        image, intrinsics = half_size(grey, intrinsics)
    out = tracker.track(seq, t_ns, image, intrinsics)
    if out is None:
        return None
    if is_keyframe:
        tracker.keyframe_seen(seq)
    ref_from_cam = None
    if out.ok:
        ref_from_cam = se3.inverse(tracker.reference.pose) @ out.pose
        if is_keyframe:  # tracking moves on to it now, whether or not mapping keeps up
            tracker.promote(seq, t_ns, grey, out.pose)  # its reference image at working resolution
    flow = (out.target, out.confidence) if out.ok and out.target is not None else None
    return Step(np.asarray(out.pose, np.float64), out.ok, out.ref_seq, ref_from_cam, flow, out.refused)


def half_size(grey: np.ndarray, intrinsics: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A working-resolution grey image and its (4,) intrinsics at half size (the resize rule of
    docs/CONVENTIONS.md)."""
    h, w = grey.shape[:2]
    small = cv2.resize(grey, (w // 2, h // 2), interpolation=cv2.INTER_AREA)
    return small, scale_intrinsics(intrinsics, 0.5, 0.5)


def predict(tracker: Tracker, t_ns: int) -> np.ndarray | None:
    """The constant-velocity pose at ``t_ns``; None before the map."""
    if tracker.reference is None:
        return None
    return np.asarray(tracker.predict(t_ns), np.float64)


def pack_reference(ref: Reference) -> dict:
    """``ref`` as the fields that cross the pipe (numpy arrays)."""
    return ref.on_host()._asdict()


def unpack_reference(packed: dict) -> Reference:
    return Reference(**packed)


class LocalTracker:
    """The tracker on the calling thread (tests, and a GPU where one process should hold the device)."""

    def __init__(self, make_tracker: Callable[[], Tracker]):
        self.tracker = make_tracker()
        self.restarts = 0

    def start(self) -> None:
        pass

    def set_reference(self, ref: Reference) -> None:
        self.tracker.set_reference(ref)

    def reset(self) -> None:
        self.tracker.reset()

    def step(self, is_keyframe: bool, seq: int, t_ns: int, image: np.ndarray, intrinsics: np.ndarray) -> Step | None:
        return step(self.tracker, is_keyframe, seq, t_ns, image, intrinsics)

    def predict(self, t_ns: int) -> np.ndarray | None:
        return predict(self.tracker, t_ns)

    def close(self) -> None:
        pass


def _serve(conn, make_tracker: Callable[[], Tracker], niceness: int, threads: int) -> None:
    """The child: answer (call, args) requests until the pipe closes."""
    limit_blas_threads(threads)  # the alignment's products: OpenBLAS threads would spin on the shared cores
    cv2.setNumThreads(threads)  # DIS too: OpenCV's own pool would spread each flow over every core
    try:  # absolute, not relative to the thread that started it
        os.setpriority(os.PRIO_PROCESS, 0, niceness)
    except (AttributeError, OSError):  # not Linux, or a higher priority than allowed: the inherited one stands
        pass
    tracker = make_tracker()
    conn.send((True, "ready"))
    calls = {"step": lambda *a: step(tracker, *a), "predict": lambda t: predict(tracker, t),
             "reference": lambda packed: tracker.set_reference(unpack_reference(packed)),
             "reset": tracker.reset}
    while True:
        try:
            name, args = conn.recv()
        except (EOFError, OSError):
            return
        try:
            conn.send((True, calls[name](*args)))
        except Exception as exc:  # noqa: BLE001 — the parent decides; the child keeps serving
            conn.send((False, f"{type(exc).__name__}: {exc}"))


class TrackerProcess:
    """The same calls as :class:`LocalTracker`, answered by a child process."""

    def __init__(self, make_tracker: Callable[[], Tracker], niceness: int = 0, threads: int = 1,
                 timeout_s: float = 30.0, name: str = "kmvipe-tracking"):
        self.make_tracker, self.niceness, self.threads = make_tracker, niceness, threads
        self.timeout_s, self.name = timeout_s, name
        self.restarts = 0  # children started again after one died or hung
        self._reference: dict | None = None  # the last reference: a new child starts from it
        self._proc = self._conn = None

    def start(self) -> None:
        spare = _take_spare(self.make_tracker, self.niceness)
        if spare is not None:  # started with the ba process, while it connected and waited for a stream
            self._proc, self._conn = spare._proc, spare._conn
            return
        self._spawn()

    def _spawn(self) -> None:
        ctx = mp.get_context("spawn")
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(target=_serve, args=(child, self.make_tracker, self.niceness, self.threads),
                                 name=self.name, daemon=True)
        self._proc.start()
        child.close()
        # up before the first frame is sent to it: a frame must not wait behind its imports
        try:
            started = self._conn.poll(self.timeout_s) and self._conn.recv() == (True, "ready")
        except (EOFError, OSError):  # it died on the way up
            started = False
        if not started:
            raise RuntimeError(f"the tracking process did not start in {self.timeout_s} s "
                               f"(exit code {self._proc.exitcode})")

    def set_reference(self, ref: Reference) -> None:
        self._reference = pack_reference(ref)
        self._call("reference", self._reference)

    def reset(self) -> None:
        self._reference = None
        self._call("reset")

    def step(self, is_keyframe: bool, seq: int, t_ns: int, image: np.ndarray, intrinsics: np.ndarray) -> Step | None:
        return self._call("step", is_keyframe, seq, t_ns, np.asarray(image), np.asarray(intrinsics, np.float64))

    def predict(self, t_ns: int) -> np.ndarray | None:
        return self._call("predict", t_ns)

    def close(self) -> None:
        if self._proc is None:
            return
        self._conn.close()
        self._proc.join(timeout=2)
        if self._proc.is_alive():
            self._proc.kill()
            self._proc.join(timeout=2)
        self._proc = self._conn = None

    def _call(self, name: str, *args):
        if self._proc is None:
            self.start()
        for attempt in (0, 1):
            try:
                self._conn.send((name, args))
                if not self._conn.poll(self.timeout_s):
                    raise TimeoutError(f"no answer in {self.timeout_s} s")
                ok, value = self._conn.recv()
            except (EOFError, OSError, TimeoutError) as exc:
                if attempt:
                    raise RuntimeError(f"tracking process failed twice: {exc}") from exc
                self._restart(exc)
                continue
            if not ok:
                raise RuntimeError(value)
            return value

    def _restart(self, why: Exception) -> None:
        self.restarts += 1
        log.error("tracking process lost; starting it again", extra={"error": str(why), "restarts": self.restarts,
                                                                     "exitcode": self._proc.exitcode})
        self._proc.kill()
        self._proc.join(timeout=2)
        self._proc = None
        self._spawn()
        if self._reference is not None:  # as mapping left it; the call in hand follows
            self._conn.send(("reference", (self._reference,)))
            if not self._conn.poll(self.timeout_s):
                raise RuntimeError("the new tracking process took no reference")
            self._conn.recv()


class _Spare:
    """One tracking process started ahead of the first stream (:func:`prewarm`)."""

    lock = threading.Lock()
    starting: threading.Thread | None = None
    ready: TrackerProcess | None = None


def prewarm(make_tracker: Callable[[], Tracker], niceness: int = 0) -> None:
    """Start a tracking process now, in the background, for the first stream to take: spawning one imports numpy,
    OpenCV and the tracker (a second on a loaded CPU), and a stream's first frames would wait for it."""
    def start() -> None:
        proc = TrackerProcess(make_tracker, niceness)
        try:
            proc._spawn()
        except RuntimeError as exc:
            log.warning("no tracking process ahead of the first stream", extra={"error": str(exc)})
            return
        with _Spare.lock:
            _Spare.ready = proc

    with _Spare.lock:
        if _Spare.starting is None:
            _Spare.starting = threading.Thread(target=start, name="tracking-prewarm", daemon=True)
            _Spare.starting.start()


def discard_spare(timeout_s: float = 10.0) -> None:
    """Close the process :func:`prewarm` started if no stream took it, once it is up (or ``timeout_s`` passed): ba
    stopped while the child still read what the parent sends a spawned process left a traceback in ba's log
    (``EOFError`` in ``multiprocessing.spawn``) when the parent's exit cut that pipe."""
    spare = _claim_spare(timeout_s)
    if spare is not None:
        spare.close()


def _claim_spare(timeout_s: float) -> TrackerProcess | None:
    """The process :func:`prewarm` started, taken from it once it is up (waiting ``timeout_s`` at most); None when
    none was started or it failed."""
    with _Spare.lock:
        starting = _Spare.starting
    if starting is None:
        return None
    starting.join(timeout=timeout_s)
    with _Spare.lock:
        spare, _Spare.ready = _Spare.ready, None
    return spare


def _same_factory(a: Callable, b: Callable) -> bool:
    if isinstance(a, functools.partial) and isinstance(b, functools.partial):
        return (a.func, a.args, a.keywords) == (b.func, b.args, b.keywords)
    return a == b


def _take_spare(make_tracker: Callable[[], Tracker], niceness: int) -> TrackerProcess | None:
    """The process :func:`prewarm` started, when it tracks with the same settings (waiting for it to come up)."""
    spare = _claim_spare(60.0)
    if spare is None or spare.niceness != niceness or not _same_factory(spare.make_tracker, make_tracker):
        if spare is not None:
            spare.close()
        return None
    return spare
