"""Pinhole projection with inverse depth and the reprojection of grid pixels between keyframes.

A pixel ``u = (x, y)`` of keyframe ``i`` with disparity ``d = 1/z`` is the homogeneous camera point
``X_i = (q, d)`` with ``q = ((x - cx)/fx, (y - cy)/fy, 1)`` (``d = 0`` is a point at infinity). Its
reprojection into keyframe ``j`` is ``pi(K, (T_j^-1 T_i X_i)[:3])`` with ``T = world_from_cam``.

Jacobians (all analytic, checked against ``torch.func.jacfwd`` in tests) are with respect to

* the left tangent ``xi_i``/``xi_j`` of ``T_i``/``T_j`` (see :mod:`services.ba.core.se3`: ``T <- exp(xi) T``,
  ``xi = (rho, phi)``). With this convention ``J_pose_j = -J_pose_i`` exactly;
* the disparity ``d`` of the source pixel;
* a **shared focal length** ``f`` with ``fx = fy = f`` (square pixels; the principal point is held fixed).

Coordinates are pixels of whatever image the intrinsics belong to (in BA: the 1/8 grid, see
docs/CONVENTIONS.md).
"""
from __future__ import annotations

from typing import NamedTuple

import torch

from services.ba.core import se3

# Points closer than this depth (same units as 1/disparity) in the target camera are marked invalid.
MIN_DEPTH = 1e-3


class Reprojection(NamedTuple):
    """Reprojection of source pixels into target keyframes, per edge ``e`` and pixel ``p``."""

    coords: torch.Tensor  # (E, P, 2) pixel (x, y) in keyframe j
    valid: torch.Tensor  # (E, P) bool: in front of camera j (does not check the image bounds)
    j_pose_focal: torch.Tensor | None  # (E, P, 2, 7) d coords / d [xi_i, f] (one buffer, see the views below)
    j_disp: torch.Tensor | None  # (E, P, 2) d coords / d disparity of the source pixel

    @property
    def j_pose_i(self) -> torch.Tensor:
        """``(E, P, 2, 6)`` d coords / d xi_i."""
        return self.j_pose_focal[..., :6]

    @property
    def j_pose_j(self) -> torch.Tensor:
        """``(E, P, 2, 6)`` d coords / d xi_j (= -d coords / d xi_i with left updates)."""
        return -self.j_pose_focal[..., :6]

    @property
    def j_focal(self) -> torch.Tensor:
        """``(E, P, 2)`` d coords / d f (fx = fy = f)."""
        return self.j_pose_focal[..., 6]


def pixel_grid(height: int, width: int, dtype=torch.float64, device=None) -> torch.Tensor:
    """Pixel centres ``(height*width, 2)`` as ``(x, y) = (col, row)``, row-major (docs/CONVENTIONS.md)."""
    rows, cols = torch.meshgrid(torch.arange(height, dtype=dtype, device=device),
                                torch.arange(width, dtype=dtype, device=device), indexing="ij")
    return torch.stack([cols, rows], dim=-1).reshape(-1, 2)


def unproject(pixels: torch.Tensor, disparity: torch.Tensor, intrinsics: torch.Tensor) -> torch.Tensor:
    """Homogeneous camera points of pixels with disparity.

    Args:
        pixels: ``(..., 2)`` pixel coordinates ``(x, y)``.
        disparity: ``(...)`` inverse depth ``1/z`` (0 = infinity).
        intrinsics: ``(4,)`` ``(fx, fy, cx, cy)`` in pixels.
    Returns:
        ``(..., 4)`` homogeneous point ``((x-cx)/fx, (y-cy)/fy, 1, d)``; divide by ``d`` for metric xyz.
    """
    if pixels.shape[-1] != 2 or intrinsics.shape != (4,):
        raise ValueError(f"pixels (...,2) and intrinsics (4,) expected, got {pixels.shape}, {intrinsics.shape}")
    fx, fy, cx, cy = intrinsics.unbind(-1)
    qx = (pixels[..., 0] - cx) / fx
    qy = (pixels[..., 1] - cy) / fy
    qx, qy, disparity = torch.broadcast_tensors(qx, qy, disparity)
    return torch.stack([qx, qy, torch.ones_like(qx), disparity], dim=-1)


def project(points: torch.Tensor, intrinsics: torch.Tensor) -> torch.Tensor:
    """Pinhole projection of camera points ``(..., 3)`` (x right, y down, z forward) -> pixels ``(..., 2)``."""
    if points.shape[-1] != 3 or intrinsics.shape != (4,):
        raise ValueError(f"points (...,3) and intrinsics (4,) expected, got {points.shape}, {intrinsics.shape}")
    fx, fy, cx, cy = intrinsics.unbind(-1)
    z = points[..., 2]
    return torch.stack([fx * points[..., 0] / z + cx, fy * points[..., 1] / z + cy], dim=-1)


def reproject(world_from_cam_i: torch.Tensor, world_from_cam_j: torch.Tensor, disparity: torch.Tensor,
              pixels: torch.Tensor, intrinsics: torch.Tensor, with_jacobians: bool = True) -> Reprojection:
    """Reproject source pixels of keyframe ``i`` with their disparities into keyframe ``j``, per edge.

    Args:
        world_from_cam_i: ``(E, 4, 4)`` source poses.
        world_from_cam_j: ``(E, 4, 4)`` target poses.
        disparity: ``(E, P)`` source disparities (inverse depth).
        pixels: ``(P, 2)`` or ``(E, P, 2)`` source pixel coordinates ``(x, y)``.
        intrinsics: ``(4,)`` ``(fx, fy, cx, cy)``; the focal Jacobian assumes ``fx = fy = f``.
        with_jacobians: also return the analytic Jacobians.
    Returns:
        :class:`Reprojection` (Jacobian fields ``None`` when ``with_jacobians`` is false).
    """
    n_edges, n_pix = disparity.shape
    if world_from_cam_i.shape != (n_edges, 4, 4) or world_from_cam_j.shape != (n_edges, 4, 4):
        raise ValueError(f"poses must be ({n_edges}, 4, 4), got {world_from_cam_i.shape}, {world_from_cam_j.shape}")
    if pixels.shape[-2:] != (n_pix, 2):
        raise ValueError(f"pixels must be (..., {n_pix}, 2), got {tuple(pixels.shape)}")
    x_i = unproject(pixels, disparity, intrinsics)  # (E, P, 4)
    q, d = x_i[..., :3], x_i[..., 3]
    rot_i, t_i = world_from_cam_i[:, :3, :3], world_from_cam_i[:, None, :3, 3]
    rot_j, t_j = world_from_cam_j[:, :3, :3], world_from_cam_j[:, None, :3, 3]
    # row-vector form (points @ R^T) keeps every product a batched (P x 3) @ (3 x 3) matmul per edge
    p_w = q @ rot_i.transpose(-1, -2) + t_i * d[..., None]  # (E, P, 3) world point, scaled by d
    x_j = (p_w - t_j * d[..., None]) @ rot_j  # (E, P, 3) camera-j point, scaled by d
    z = x_j[..., 2]
    valid = z > MIN_DEPTH * d
    z_safe = torch.where(z.abs() < 1e-12, torch.full_like(z, 1e-12), z)
    fx, fy, cx, cy = intrinsics.unbind(-1)
    inv_z = 1 / z_safe
    u_n, v_n = x_j[..., 0] * inv_z, x_j[..., 1] * inv_z
    coords = torch.stack([fx * u_n + cx, fy * v_n + cy], -1)
    if not with_jacobians:
        return Reprojection(coords, valid, None, None)

    zeros = torch.zeros_like(z)
    d_proj = torch.stack([fx * inv_z, zeros, -fx * u_n * inv_z,
                          zeros, fy * inv_z, -fy * v_n * inv_z], -1).reshape(n_edges, n_pix, 2, 3)
    # a = d_proj @ R_j^T: derivative of the pixel w.r.t. the (scaled) world point
    a = (d_proj.reshape(n_edges, 2 * n_pix, 3) @ rot_j.transpose(-1, -2)).reshape(n_edges, n_pix, 2, 3)
    # left tangent of T_i moves the world point by [d I, -[p_w]x] xi, and a^T [p]x = (a x p)^T
    jac = torch.empty(n_edges, n_pix, 2, 7, dtype=a.dtype, device=a.device)
    torch.mul(a, d[..., None, None], out=jac[..., :3])
    jac[..., 3:6] = torch.linalg.cross(p_w[..., None, :].expand_as(a), a, dim=-1)
    j_disp = (a * (t_i - t_j)[:, :, None, :]).sum(-1)
    dq_df = torch.stack([-q[..., 0] / fx, -q[..., 1] / fy, zeros], -1)  # (E, P, 3), fx = fy = f
    dxj_df = dq_df @ (rot_j.transpose(-1, -2) @ rot_i).transpose(-1, -2)
    jac[..., 6] = (d_proj * dxj_df[..., None, :]).sum(-1) + torch.stack([u_n, v_n], -1)
    return Reprojection(coords, valid, jac, j_disp)
