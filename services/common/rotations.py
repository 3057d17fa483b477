"""Rotation matrices ↔ Hamilton quaternions in (x, y, z, w) order, vectorised numpy — the one place files
(TUM, COLMAP) get their quaternions from. The torch versions in ``services/ba/core/se3.py`` serve the solver."""
from __future__ import annotations

import numpy as np


def quaternion_to_rotation(q: np.ndarray) -> np.ndarray:
    """``(N, 4)`` Hamilton quaternions ``(x, y, z, w)`` (normalised here) -> ``(N, 3, 3)`` rotations."""
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = q.T
    rot = np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
                    2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
                    2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=-1)
    return rot.reshape(-1, 3, 3)


def rotation_to_quaternion(rot: np.ndarray) -> np.ndarray:
    """``(N, 3, 3)`` rotations -> ``(N, 4)`` Hamilton quaternions ``(x, y, z, w)`` with ``w >= 0``."""
    m = np.asarray(rot, np.float64)
    if m.ndim != 3 or m.shape[1:] != (3, 3):
        raise ValueError(f"rotations must be (N, 3, 3), got {m.shape}")
    # The symmetric 4x4 matrix whose top eigenvector is the quaternion (Bar-Itzhack): robust for all angles.
    k = np.empty((len(m), 4, 4))
    k[:, 0, 0] = m[:, 0, 0] - m[:, 1, 1] - m[:, 2, 2]
    k[:, 1, 1] = m[:, 1, 1] - m[:, 0, 0] - m[:, 2, 2]
    k[:, 2, 2] = m[:, 2, 2] - m[:, 0, 0] - m[:, 1, 1]
    k[:, 3, 3] = m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2]
    k[:, 0, 1] = k[:, 1, 0] = m[:, 0, 1] + m[:, 1, 0]
    k[:, 0, 2] = k[:, 2, 0] = m[:, 0, 2] + m[:, 2, 0]
    k[:, 1, 2] = k[:, 2, 1] = m[:, 1, 2] + m[:, 2, 1]
    k[:, 0, 3] = k[:, 3, 0] = m[:, 2, 1] - m[:, 1, 2]
    k[:, 1, 3] = k[:, 3, 1] = m[:, 0, 2] - m[:, 2, 0]
    k[:, 2, 3] = k[:, 3, 2] = m[:, 1, 0] - m[:, 0, 1]
    _, vecs = np.linalg.eigh(k / 3.0)
    q = vecs[:, :, -1]
    return np.where(q[:, 3:4] < 0, -q, q)
