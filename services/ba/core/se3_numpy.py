"""SE(3) on single ``(4, 4)`` numpy poses: the part of :mod:`services.ba.core.se3` that frame tracking uses, for
the tracking process, which runs without torch (importing it costs a process ~200 MB; docs/ARCHITECTURE.md).

Same conventions as :mod:`services.ba.core.se3` (``world_from_cam``, tangent ``(rho, phi)``, left updates
``T <- exp(xi) T``) and the same closed forms; tests check both agree to round-off.
"""
from __future__ import annotations

import numpy as np

SMALL_ANGLE = 1e-4  # below it V and V^-1 use their Taylor series (as services.ba.core.se3)


def hat(v: np.ndarray) -> np.ndarray:
    """``(3,) -> (3, 3)`` skew-symmetric matrix with ``hat(a) @ b = a x b``."""
    x, y, z = v
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def _left_jacobian_coeffs(theta2: float) -> tuple[float, float, float]:
    """A = sin t / t, B = (1 - cos t) / t^2, C = (t - sin t) / t^3."""
    if theta2 < SMALL_ANGLE**2:
        return (1 - theta2 / 6 + theta2**2 / 120, 0.5 - theta2 / 24 + theta2**2 / 720,
                1 / 6 - theta2 / 120 + theta2**2 / 5040)
    t = np.sqrt(theta2)
    return np.sin(t) / t, (1 - np.cos(t)) / theta2, (t - np.sin(t)) / (theta2 * t)


def so3_log(rot: np.ndarray) -> np.ndarray:
    """Rotation vector ``(3,)`` of a rotation matrix, angle in ``[0, pi]``, by the quaternion (stable at 0 and
    near pi; an arccos of the trace loses half the digits of a small angle)."""
    m = rot
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    # four candidate quaternions (x, y, z, w); the one with the largest pivot is the best conditioned
    cands = np.array([
        [m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1], 1 + tr],
        [1 + m[0, 0] - m[1, 1] - m[2, 2], m[0, 1] + m[1, 0], m[0, 2] + m[2, 0], m[2, 1] - m[1, 2]],
        [m[0, 1] + m[1, 0], 1 - m[0, 0] + m[1, 1] - m[2, 2], m[1, 2] + m[2, 1], m[0, 2] - m[2, 0]],
        [m[0, 2] + m[2, 0], m[1, 2] + m[2, 1], 1 - m[0, 0] - m[1, 1] + m[2, 2], m[1, 0] - m[0, 1]]])
    q = cands[int(np.argmax([1 + tr, cands[1, 0], cands[2, 1], cands[3, 2]]))]
    q = q / np.linalg.norm(q)
    if q[3] < 0:
        q = -q
    v, w = q[:3], q[3]
    n = float(np.linalg.norm(v))
    if n < 1e-8:
        w = max(w, 1e-12)
        return v * (2 / w * (1 - n**2 / (3 * w**2)))
    return v * (2 * np.arctan2(n, w) / n)


def _make(rot: np.ndarray, trans: np.ndarray) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = rot, trans
    return pose


def exp(xi: np.ndarray) -> np.ndarray:
    """Tangent ``(6,)`` ordered ``(rho, phi)`` -> ``(4, 4)``."""
    xi = np.asarray(xi, np.float64)
    rho, phi = xi[:3], xi[3:]
    a, b, c = _left_jacobian_coeffs(float(phi @ phi))
    k = hat(phi)
    v = np.eye(3) + b * k + c * (k @ k)
    return _make(np.eye(3) + a * k + b * (k @ k), v @ rho)


def log(pose: np.ndarray) -> np.ndarray:
    """``(4, 4) -> (6,)`` ordered ``(rho, phi)``; the inverse of :func:`exp`."""
    phi = so3_log(pose[:3, :3])
    theta2 = float(phi @ phi)
    a, b, _ = _left_jacobian_coeffs(theta2)
    # V^-1 = I - K/2 + D K^2 with D = (1 - A / (2 B)) / theta^2
    d = 1 / 12 + theta2 / 720 if theta2 < SMALL_ANGLE**2 else (1 - a / (2 * b)) / theta2
    k = hat(phi)
    return np.concatenate([(np.eye(3) - 0.5 * k + d * (k @ k)) @ pose[:3, 3], phi])


def inverse(pose: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform ``(4, 4)``."""
    rot_t = pose[:3, :3].T
    return _make(rot_t, -rot_t @ pose[:3, 3])


def orthonormalize(pose: np.ndarray, steps: int = 2) -> np.ndarray:
    """The rotation block pulled back onto SO(3) by the Newton-Schulz polar iteration of
    :func:`services.ba.core.se3.orthonormalize` (why every update and prediction goes through it: there)."""
    rot = pose[:3, :3]
    for _ in range(steps):
        rot = 0.5 * rot @ (3 * np.eye(3) - rot.T @ rot)
    return _make(rot, pose[:3, 3])


def retract(pose: np.ndarray, xi: np.ndarray) -> np.ndarray:
    """Left update ``exp(xi) @ pose``, kept rigid."""
    return orthonormalize(exp(xi) @ pose)
