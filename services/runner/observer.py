"""What ``kmvipe run`` sees on the bus while a stream runs (frames, poses as they first arrive, ba's refined
intrinsics, each stage's EOS) and the live-operation figures of its summary computed from that: posed fraction,
capture → pose latency, drops per stage, end-of-stream time, each service's CPU and RSS."""
from __future__ import annotations

import logging
import threading
import time
from typing import TYPE_CHECKING

import numpy as np

from ..common.bus import Delivery
from ..common.rotations import is_rigid
from ..common.camera import scale_intrinsics
from ..common.schema import Eos, Frame, Intrinsics, Keyframe, Poses
from . import children as kids
from .resources import ResourceMonitor

if TYPE_CHECKING:
    from .pipeline import RunReport

log = logging.getLogger(__name__)


class Observer:
    """What the runner sees on the bus (callbacks run on Zenoh threads)."""

    def __init__(self, last_stage: str):
        self.lock = threading.Lock()
        self.last_stage = last_stage
        self.frames = self.keyframes = 0
        self.last_frame_seq = -1
        self.image_size: tuple[int, int] | None = None  # the source frames' (width, height)
        self.intrinsics: Intrinsics | None = None  # ba's latest refined intrinsics (working resolution)
        self.poses: dict[int, tuple[int, object]] = {}
        self.mapped: set[int] = set()  # frames whose pose mapping has revised (a later tracking pose never wins)
        self.seen_at: dict[int, float] = {}  # frame seq → monotonic time the runner saw it on the bus
        self.first_pose: dict[int, tuple[float, int, object]] = {}  # seq → (arrival, stamp, pose) of its first pose
        self.first_tracked: set[int] = set()  # frames whose first pose came from tracking (not mapping)
        self.first_provisional: set[int] = set()  # ... tracking's rotation-only pose from before the map
        self.eos: dict[str, Eos] = {}
        self.eos_at: dict[str, float] = {}
        self.done = threading.Event()
        self.last_activity = time.monotonic()

    def on_message(self, delivery: Delivery) -> None:
        msg = delivery.msg
        now = time.monotonic()
        with self.lock:
            self.last_activity = now
            if isinstance(msg, Frame):
                self.frames += 1
                self.last_frame_seq = msg.seq
                self.seen_at.setdefault(msg.seq, now)
                self.image_size = (msg.width, msg.height)
            elif isinstance(msg, Keyframe):
                self.keyframes += 1
            elif isinstance(msg, Poses):
                rigid = is_rigid(msg.poses)
                for seq, stamp, pose, ok in zip(msg.frame_seqs, msg.stamps_ns, msg.poses, rigid):
                    if not ok:  # no quaternion exists for it: the trajectory files could not be written
                        log.warning("a pose that is not a rigid transform ignored", extra={"seq": int(seq)})
                        continue
                    if int(seq) not in self.first_pose:
                        self.first_pose[int(seq)] = (now, int(stamp), pose)
                        if msg.tracked:
                            self.first_tracked.add(int(seq))
                        if msg.provisional:
                            self.first_provisional.add(int(seq))
                    if msg.tracked and int(seq) in self.mapped:
                        continue
                    self.poses[int(seq)] = (int(stamp), pose)
                    if not msg.tracked:
                        self.mapped.add(int(seq))
            elif isinstance(msg, Intrinsics):
                self.intrinsics = msg
            elif isinstance(msg, Eos):
                self.eos[msg.stage] = msg
                self.eos_at[msg.stage] = now
                if msg.stage == self.last_stage:
                    self.done.set()


def settle(observer: Observer, grace_s: float = 2.0) -> None:
    """Zenoh delivers different keys on different threads: the last stage's EOS can be handled while the last
    frames' callbacks are still running. Wait (briefly) until the runner has counted every frame ingest says it
    published, so the summary does not under-count."""
    deadline = time.monotonic() + grace_s
    while time.monotonic() < deadline:
        with observer.lock:
            ingest_eos = observer.eos.get("ingest")
            if ingest_eos is None or observer.frames >= ingest_eos.count:
                return
        time.sleep(0.02)


def refined_intrinsics(observer: Observer) -> list[float] | None:
    """ba's latest refined intrinsics in the source frames' pixels (fx, fy, cx, cy), None before any."""
    k, size = observer.intrinsics, observer.image_size
    if k is None or size is None or k.width <= 0 or k.height <= 0:
        return None
    return [round(float(v), 3) for v in scale_intrinsics(k.intrinsics, size[0] / k.width, size[1] / k.height)]


STAGES = ("ingest", "features", "ba", "mapstore")  # the streaming stages, each ends with an EOS


def fill_report(report: "RunReport", observer: Observer, monitor: ResourceMonitor) -> None:
    report.frames = observer.frames
    report.keyframes = observer.keyframes
    report.posed_frames = len(observer.poses)
    ingest_eos = observer.eos.get("ingest")
    if ingest_eos is not None:
        report.frames_dropped_or_lost = max(0, ingest_eos.seq + 1 - observer.frames)
    report.fps = report.frames / report.duration_s if report.duration_s else 0.0
    # live operation: poses as they first arrived, against every frame ingest read
    report.frames_read = ingest_eos.seq + 1 if ingest_eos is not None else max(observer.last_frame_seq + 1, 0)
    posed = [seq for seq in observer.first_pose if 0 <= seq < report.frames_read]
    report.posed_fraction = len(posed) / report.frames_read if report.frames_read else None
    latencies = [max(0.0, observer.first_pose[seq][0] - observer.seen_at[seq]) * 1e3
                 for seq in posed if seq in observer.seen_at]
    if latencies:
        report.pose_latency_ms = {
            "p50": round(float(np.percentile(latencies, 50)), 1), "p99": round(float(np.percentile(latencies, 99)), 1),
            "max": round(float(np.max(latencies)), 1), "n": len(latencies)}
    ran = set(report.services_ran)
    report.drops = {stage: (observer.eos[stage].dropped if stage in observer.eos else None)
                    for stage in STAGES if stage in ran}
    if "features" in observer.eos:
        report.codes_skipped = observer.eos["features"].codes_skipped
        report.frames_lost = observer.eos["features"].lost
    report.intrinsics = refined_intrinsics(observer)
    report.image_size = None if observer.image_size is None else list(observer.image_size)
    if "ba" in observer.eos and observer.eos["ba"].views_lost is not None:
        report.views_lost = [[int(a), int(b)] for a, b in observer.eos["ba"].views_lost]
    if "ba" in observer.eos:
        report.frames_strayed = observer.eos["ba"].frames_strayed
    if "ingest" in observer.eos_at and observer.last_stage in observer.eos_at:
        report.end_of_stream_s = round(observer.eos_at[observer.last_stage] - observer.eos_at["ingest"], 3)
        report.end_of_stream_stages = {
            stage: {"after_ingest_s": round(observer.eos_at[stage] - observer.eos_at["ingest"], 3),
                    "work_s": observer.eos[stage].work_s}
            for stage in STAGES if stage in observer.eos_at and stage != "ingest"}
    usage = monitor.report()
    report.services = {name: usage[name] for name in kids.PIPELINE if name in usage}  # in chain order
    report.rss_total_peak_mb = round(monitor.rss_total_peak_mb, 1)
    report.pss_total_peak_mb = None if monitor.pss_total_peak_mb is None else round(monitor.pss_total_peak_mb, 1)
    report.rss_mb_at_frames = list(monitor.series)
