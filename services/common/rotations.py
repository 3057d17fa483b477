"""Rotation matrices ↔ Hamilton quaternions in (x, y, z, w) order — the one place files and messages (TUM, COLMAP,
ROS) get their quaternions from, so they all take the same sign. scipy does the maths; the torch versions in
``services/ba/core/se3.py`` serve the solver (batched on its device, differentiable)."""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def quaternion_to_rotation(q: np.ndarray) -> np.ndarray:
    """``(..., 4)`` Hamilton quaternions ``(x, y, z, w)`` (normalised here) -> ``(..., 3, 3)`` rotations."""
    return Rotation.from_quat(q).as_matrix()


def rotation_to_quaternion(rot: np.ndarray) -> np.ndarray:
    """``(..., 3, 3)`` rotations -> ``(..., 4)`` Hamilton quaternions ``(x, y, z, w)`` with ``w >= 0`` (one sign
    of the two that give each rotation, so a file is the same for the same poses)."""
    return Rotation.from_matrix(rot).as_quat(canonical=True)


def quaternion_wxyz(rot: np.ndarray) -> np.ndarray:
    """``(..., 3, 3)`` rotations -> ``(..., 4)`` quaternions ``(w, x, y, z)``, ``w >= 0``: COLMAP's order."""
    return np.roll(rotation_to_quaternion(rot), 1, axis=-1)


def rotation_from_wxyz(q: np.ndarray) -> np.ndarray:
    """``(..., 4)`` quaternions ``(w, x, y, z)`` (normalised here) -> ``(..., 3, 3)`` rotations."""
    return quaternion_to_rotation(np.roll(np.asarray(q, np.float64), -1, axis=-1))


def is_rigid(poses: np.ndarray, tol: float = 1e-3) -> np.ndarray:
    """``(..., 4, 4)`` -> ``(...)`` bool: finite, a rotation block on SO(3) within ``tol`` (RᵀR = I, det R > 0)
    and the last row (0, 0, 0, 1). Anything else is not a pose: no quaternion exists for it, and one such matrix
    made a run's TUM writer fail at its end."""
    poses = np.asarray(poses, np.float64)
    finite = np.isfinite(poses).all(axis=(-2, -1))
    safe = np.where(finite[..., None, None], poses, 0.0)
    rot = safe[..., :3, :3]
    gram = np.abs(np.swapaxes(rot, -1, -2) @ rot - np.eye(3)).max(axis=(-2, -1))
    bottom = np.abs(safe[..., 3, :] - np.array([0.0, 0.0, 0.0, 1.0])).max(axis=-1)
    return finite & (gram <= tol) & (np.linalg.det(rot) > 0) & (bottom <= tol)

