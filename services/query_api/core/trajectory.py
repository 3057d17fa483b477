"""The latest camera poses of each stream, as BA publishes and revises them.

Poses are ``world_from_cam`` (4, 4) float64 (docs/CONVENTIONS.md); a later message for the same frame seq
replaces the earlier pose. TUM lines are ``timestamp tx ty tz qx qy qz qw`` with the timestamp in seconds.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


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


def quaternion_xyzw(rotation: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotation matrices → (N, 4) unit quaternions (x, y, z, w), w ≥ 0 (Hamilton)."""
    r = np.asarray(rotation, np.float64)
    if r.ndim != 3 or r.shape[1:] != (3, 3):
        raise ValueError(f"rotation must be (N, 3, 3), got {r.shape}")
    # Shepperd: pick the largest of (w, x, y, z) magnitudes for numerical stability
    tr = np.trace(r, axis1=1, axis2=2)
    cand = np.stack([tr, r[:, 0, 0], r[:, 1, 1], r[:, 2, 2]], axis=1)
    k = np.argmax(cand, axis=1)
    q = np.zeros((len(r), 4))
    for i, (m, j) in enumerate(zip(r, k)):
        if j == 0:
            s = 2.0 * np.sqrt(max(1.0 + tr[i], 1e-300))
            q[i] = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s]
        else:
            a, b, c = (j - 1), j % 3, (j + 1) % 3
            s = 2.0 * np.sqrt(max(1.0 + m[a, a] - m[b, b] - m[c, c], 1e-300))
            v = np.zeros(4)
            v[a] = 0.25 * s
            v[b] = (m[b, a] + m[a, b]) / s
            v[c] = (m[c, a] + m[a, c]) / s
            v[3] = (m[c, b] - m[b, c]) / s
            q[i] = v
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return np.where(q[:, 3:4] < 0, -q, q)


def tum_text(traj: Trajectory) -> str:
    """TUM trajectory text (one line per frame, seconds with 9 decimals)."""
    if not len(traj.seqs):
        return ""
    q = quaternion_xyzw(traj.poses[:, :3, :3])
    t = traj.poses[:, :3, 3]
    lines = [f"{ns // 1_000_000_000}.{ns % 1_000_000_000:09d} " + " ".join(f"{v:.9g}" for v in (*ti, *qi))
             for ns, ti, qi in zip(traj.stamps_ns.tolist(), t, q)]
    return "\n".join(lines) + "\n"
