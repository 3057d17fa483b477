"""The latest camera poses of each stream, as BA publishes and revises them.

Poses are ``world_from_cam`` (4, 4) float64 (docs/CONVENTIONS.md); a later message for the same frame seq
replaces the earlier pose. TUM lines are ``timestamp tx ty tz qx qy qz qw`` with the timestamp in seconds.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...evaluation import trajectory_io


@dataclass(frozen=True)
class Trajectory:
    """Frames of one stream sorted by seq."""

    seqs: np.ndarray  # (N,) int64
    stamps_ns: np.ndarray  # (N,) int64
    poses: np.ndarray  # (N, 4, 4) float64 world_from_cam


class PoseBook:
    """Per-frame poses of one stream, at most ``capacity`` frames (the oldest seqs are dropped first)."""

    def __init__(self, capacity: int = 100_000):
        self.capacity = capacity
        self._poses: dict[int, tuple[int, np.ndarray]] = {}
        self.final = False

    def __len__(self) -> int:
        return len(self._poses)

    def update(self, seqs: np.ndarray, stamps_ns: np.ndarray, poses: np.ndarray, final: bool = False) -> None:
        """Merge (N,) seqs, (N,) stamps and (N, 4, 4) poses; newer values win."""
        n = len(seqs)
        if np.shape(stamps_ns) != (n,) or np.shape(poses) != (n, 4, 4):
            raise ValueError(f"need (N,) stamps and (N, 4, 4) poses for N={n}, got {np.shape(stamps_ns)}, {np.shape(poses)}")
        for s, t, p in zip(np.asarray(seqs).tolist(), np.asarray(stamps_ns).tolist(), np.asarray(poses, np.float64)):
            self._poses[int(s)] = (int(t), p.copy())
        if len(self._poses) > self.capacity:
            for s in sorted(self._poses)[: len(self._poses) - self.capacity]:
                del self._poses[s]
        self.final = self.final or final

    def trajectory(self) -> Trajectory:
        seqs = np.array(sorted(self._poses), np.int64)
        stamps = np.array([self._poses[s][0] for s in seqs.tolist()], np.int64)
        poses = np.stack([self._poses[s][1] for s in seqs.tolist()]) if len(seqs) else np.zeros((0, 4, 4))
        return Trajectory(seqs, stamps, poses)


def tum_text(traj: Trajectory) -> str:
    """TUM trajectory text (one line per frame, seconds with 9 decimals, exact from the nanosecond stamps)."""
    stamps = [trajectory_io.tum_timestamp(ns) for ns in traj.stamps_ns.tolist()]
    return trajectory_io.tum_text(stamps, traj.poses)
