"""Motion-only alignment: the pose of one camera from flow targets of fixed keyframes (6-dof Gauss-Newton).

Keyframe ``k`` (fixed pose and grid disparity) sees its grid pixel ``u`` land at ``target_k(u)`` in the
camera being aligned; the camera pose ``T = world_from_cam`` minimises the Huber-weighted, confidence-weighted
``sum |target - reproj_k(u; T)|^2`` with left updates ``T <- exp(xi) T`` (services/ba/core/se3.py).

numpy, not torch: the tracking process runs it on every frame without importing torch (a 6-dof problem over a few
thousand grid cells gains nothing from a device). Mapping passes its graph's tensors; they are read on the host.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from services.ba.core import se3_numpy
from services.ba.core.host_arrays import as_numpy
from services.ba.core.projective_numpy import pixel_grid, reproject_into
from services.ba.frontend.params import MotionParams


class MotionResult(NamedTuple):
    """Aligned pose and diagnostics."""

    pose: np.ndarray  # (4, 4) float64 world_from_cam of the aligned camera
    rms: float  # weighted RMS flow residual at the result (grid px)
    weight: float  # total weight of the residuals used (about the number of trusted pixels)
    ok: bool  # False when too little weight was left to align (pose is then the initial one)
    steps: int = 0  # Gauss-Newton steps taken (at most MotionParams.iterations)


def _linearise(pose, kf_poses, disp, pixels, intr, targets, conf, params: MotionParams, with_jac: bool):
    rp = reproject_into(kf_poses, pose, disp, pixels, intr, with_jac)
    resid = targets - rp.coords  # (M, P, 2)
    norm = np.linalg.norm(resid, axis=-1)
    huber = np.where(norm <= params.huber, 1.0, params.huber / np.maximum(norm, 1e-12))
    weight = conf * rp.valid * huber  # (M, P)
    return rp, resid, weight


def align(pose, kf_poses, kf_disparity, targets, confidence, intrinsics, params: MotionParams) -> MotionResult:
    """Align one camera to ``M`` fixed keyframes (numpy arrays or torch tensors; float64 inside).

    Args:
        pose: ``(4, 4)`` initial world_from_cam of the camera.
        kf_poses: ``(M, 4, 4)`` world_from_cam of the keyframes (held fixed).
        kf_disparity: ``(M, h, w)`` keyframe grid disparities (held fixed).
        targets: ``(M, h, w, 2)`` where each keyframe grid pixel lands in the camera (grid px, (x, y)).
        confidence: ``(M, h, w)`` flow confidence in [0, 1].
        intrinsics: ``(4,)`` grid intrinsics (fx, fy, cx, cy), shared by keyframes and camera.
    Returns:
        :class:`MotionResult`, its pose a numpy array.
    """
    pose, kf_poses, kf_disparity = as_numpy(pose), as_numpy(kf_poses), as_numpy(kf_disparity)
    targets, confidence, intrinsics = as_numpy(targets), as_numpy(confidence), as_numpy(intrinsics)
    m, h, w = kf_disparity.shape
    if pose.shape != (4, 4) or kf_poses.shape != (m, 4, 4):
        raise ValueError(f"pose (4,4) and kf_poses ({m},4,4) expected, got {pose.shape}, {kf_poses.shape}")
    if targets.shape != (m, h, w, 2) or confidence.shape != (m, h, w):
        raise ValueError(f"targets ({m},{h},{w},2) and confidence ({m},{h},{w}) expected")
    pixels = pixel_grid(h, w)
    disp, tgt, conf = kf_disparity.reshape(m, -1), targets.reshape(m, -1, 2), confidence.reshape(m, -1)
    start = pose
    steps = 0
    for steps in range(1, params.iterations + 1):
        rp, resid, weight = _linearise(pose, kf_poses, disp, pixels, intrinsics, tgt, conf, params, True)
        if float(weight.sum()) < params.min_weight:
            return MotionResult(start, float("nan"), float(weight.sum()), False)
        jac = rp.jac_rows.reshape(6, -1)  # (6, M * 2 * P) d coords / d xi of the camera
        wj = jac * np.repeat(weight[:, None, :], 2, axis=1).reshape(-1)  # each pixel's weight on its x and y rows
        hess = wj @ jac.T
        grad = wj @ resid.transpose(0, 2, 1).reshape(-1)
        hess = hess + params.damping * np.diag(np.diag(hess)) + 1e-12 * np.eye(6)
        step = np.linalg.solve(hess, grad)
        pose = se3_numpy.retract(pose, step)
        # the step moved the trusted pixels by a thousandth of a grid pixel on average: converged. Tracking's start
        # (a constant-velocity prediction) is usually a few steps from the answer, and every frame of a live camera
        # would pay for the iterations after that
        moved = (weight * np.linalg.norm((step @ jac).reshape(m, 2, -1), axis=1)).sum() / weight.sum()
        if float(moved) < params.step_tol:
            break
    _, resid, weight = _linearise(pose, kf_poses, disp, pixels, intrinsics, tgt, conf, params, False)
    total = float(weight.sum())
    rms = float(np.sqrt((weight * (resid**2).sum(-1)).sum() / max(total, 1e-12)))
    if not (bool(np.isfinite(pose).all()) and total >= params.min_weight):
        return MotionResult(start, rms, total, False, steps)
    return MotionResult(pose, rms, total, True, steps)
