"""The camera trajectory as the bridge keeps it (pure): every frame's latest pose, and which frames still need
their transform.

ba publishes a frame's pose first from tracking (``tracked``), then revisions from mapping, often of many frames at
once. A transform goes out once per frame, in frame order, as soon as the frame has its first pose: tf2 keeps
the newest transforms, and re-sending old stamps would only fill its buffer. The path always shows every
frame's latest pose; a tracked pose never replaces one mapping has revised (as the runner reads them).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class NewPoses:
    """Frames that got their first pose from one ``Poses`` message, in frame order."""

    seqs: np.ndarray  # (M,) int64
    stamps_ns: np.ndarray  # (M,) int64
    world_from_cam: np.ndarray  # (M, 4, 4) float64


@dataclass
class Trajectory:
    """Latest pose per frame seq, for one session of one stream."""

    session: str = ""
    poses: dict[int, tuple[int, np.ndarray]] = field(default_factory=dict)  # seq -> (stamp_ns, world_from_cam)
    mapped: set[int] = field(default_factory=set)
    last_sent: int = -1  # the highest seq whose transform went out
    changed: bool = False  # poses changed since the path was last taken

    def update(self, seqs: np.ndarray, stamps_ns: np.ndarray, world_from_cam: np.ndarray, tracked: bool,
               session: str = "") -> NewPoses:
        """Take the poses of one ``Poses`` message; returns the frames newer than every frame sent before.
        A new ``session`` (the source restarted: a new world) starts the trajectory afresh."""
        if session != self.session:
            self.session, self.last_sent, self.changed = session, -1, False
            self.poses, self.mapped = {}, set()
        for seq, stamp, pose in zip(np.asarray(seqs).tolist(), np.asarray(stamps_ns).tolist(), world_from_cam):
            if tracked and seq in self.mapped:
                continue
            self.poses[seq] = (stamp, np.asarray(pose, np.float64))
            if not tracked:
                self.mapped.add(seq)
            self.changed = True
        fresh = sorted(s for s in np.asarray(seqs).tolist() if s > self.last_sent and s in self.poses)
        if fresh:
            self.last_sent = fresh[-1]
        return NewPoses(np.asarray(fresh, np.int64), np.asarray([self.poses[s][0] for s in fresh], np.int64),
                        np.asarray([self.poses[s][1] for s in fresh], np.float64).reshape(-1, 4, 4))

    def take_path(self) -> tuple[np.ndarray, np.ndarray]:
        """Every frame's latest pose in frame order: ``(stamps_ns (N,), world_from_cam (N, 4, 4))``; clears
        :attr:`changed`."""
        self.changed = False
        order = sorted(self.poses)
        return (np.asarray([self.poses[s][0] for s in order], np.int64),
                np.asarray([self.poses[s][1] for s in order], np.float64).reshape(-1, 4, 4))


def subsample(n: int, limit: int) -> np.ndarray:
    """Indices of at most ``limit`` of ``n`` items, evenly spread (all of them when ``n <= limit``)."""
    if n <= limit:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, limit).round().astype(np.int64))
