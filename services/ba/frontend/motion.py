"""Motion-only alignment: the pose of one camera from flow targets of fixed keyframes (6-dof Gauss-Newton).

Keyframe ``k`` (fixed pose and grid disparity) sees its grid pixel ``u`` land at ``target_k(u)`` in the
camera being aligned; the camera pose ``T = world_from_cam`` minimises the Huber-weighted, confidence-weighted
``sum |target - reproj_k(u; T)|^2`` with left updates ``T <- exp(xi) T`` (services/ba/core/se3.py).
"""
from __future__ import annotations

from typing import NamedTuple

import torch

from services.ba.core import projective, se3
from services.ba.frontend.params import MotionParams


class MotionResult(NamedTuple):
    """Aligned pose and diagnostics."""

    pose: torch.Tensor  # (4, 4) float64 world_from_cam of the aligned camera
    rms: float  # weighted RMS flow residual at the result (grid px)
    weight: float  # total weight of the residuals used (about the number of trusted pixels)
    ok: bool  # False when too little weight was left to align (pose is then the initial one)
    steps: int = 0  # Gauss-Newton steps taken (at most MotionParams.iterations)


def _linearise(pose, kf_poses, disp, pixels, intr, targets, conf, params: MotionParams, with_jac: bool):
    m = kf_poses.shape[0]
    rp = projective.reproject(kf_poses, pose.expand(m, 4, 4), disp, pixels, intr, with_jac)
    resid = targets - rp.coords  # (M, P, 2)
    norm = resid.norm(dim=-1)
    huber = torch.where(norm <= params.huber, torch.ones_like(norm), params.huber / norm.clamp_min(1e-12))
    weight = conf * rp.valid * huber  # (M, P)
    return rp, resid, weight


def align(pose: torch.Tensor, kf_poses: torch.Tensor, kf_disparity: torch.Tensor, targets: torch.Tensor,
          confidence: torch.Tensor, intrinsics: torch.Tensor, params: MotionParams) -> MotionResult:
    """Align one camera to ``M`` fixed keyframes.

    Args:
        pose: ``(4, 4)`` float64 initial world_from_cam of the camera.
        kf_poses: ``(M, 4, 4)`` float64 world_from_cam of the keyframes (held fixed).
        kf_disparity: ``(M, h, w)`` keyframe grid disparities (held fixed).
        targets: ``(M, h, w, 2)`` where each keyframe grid pixel lands in the camera (grid px, (x, y)).
        confidence: ``(M, h, w)`` flow confidence in [0, 1].
        intrinsics: ``(4,)`` grid intrinsics (fx, fy, cx, cy), shared by keyframes and camera.
    """
    m, h, w = kf_disparity.shape
    if pose.shape != (4, 4) or kf_poses.shape != (m, 4, 4):
        raise ValueError(f"pose (4,4) and kf_poses ({m},4,4) expected, got {pose.shape}, {kf_poses.shape}")
    if targets.shape != (m, h, w, 2) or confidence.shape != (m, h, w):
        raise ValueError(f"targets ({m},{h},{w},2) and confidence ({m},{h},{w}) expected")
    dtype, device = kf_poses.dtype, kf_poses.device
    pixels = projective.pixel_grid(h, w, dtype, device)
    disp, tgt = kf_disparity.reshape(m, -1).to(dtype), targets.reshape(m, -1, 2).to(dtype)
    conf = confidence.reshape(m, -1).to(dtype)
    pose = start = pose.to(dtype)
    steps = 0
    for steps in range(1, params.iterations + 1):
        rp, resid, weight = _linearise(pose, kf_poses, disp, pixels, intrinsics, tgt, conf, params, True)
        if float(weight.sum()) < params.min_weight:
            return MotionResult(start, float("nan"), float(weight.sum()), False)
        jac = rp.j_pose_j.reshape(-1, 6)  # (M * P * 2, 6) d coords / d xi of the camera
        wj = weight.repeat_interleave(2, dim=-1).reshape(-1, 1) * jac  # each pixel's weight on its x and y rows
        hess = wj.T @ jac  # a matrix product, not an einsum: tracking runs this on every frame
        grad = wj.T @ resid.reshape(-1)
        hess = hess + params.damping * torch.diag(hess.diagonal()) + 1e-12 * torch.eye(6, dtype=dtype, device=device)
        step = torch.linalg.solve(hess, grad)
        pose = se3.retract(pose, step)
        # the step moved the trusted pixels by a thousandth of a grid pixel on average: converged. Tracking's start
        # (a constant-velocity prediction) is usually a few steps from the answer, and every frame of a live camera
        # would pay for the iterations after that
        moved = (weight * (jac @ step).reshape(weight.shape + (2,)).norm(dim=-1)).sum() / weight.sum()
        if float(moved) < params.step_tol:
            break
    _, resid, weight = _linearise(pose, kf_poses, disp, pixels, intrinsics, tgt, conf, params, False)
    total = float(weight.sum())
    rms = float(((weight * (resid**2).sum(-1)).sum() / max(total, 1e-12)).sqrt())
    if not (bool(torch.isfinite(pose).all()) and total >= params.min_weight):
        return MotionResult(start, rms, total, False, steps)
    return MotionResult(pose, rms, total, True, steps)
