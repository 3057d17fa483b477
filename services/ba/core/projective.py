"""Pinhole projection with inverse depth and the reprojection of grid pixels between keyframes.

A pixel ``u = (x, y)`` of keyframe ``i`` with disparity ``d = 1/z`` is the homogeneous camera point
``X_i = (q, d)`` with ``q = ((x - cx)/fx, (y - cy)/fy, 1)`` (``d = 0`` is a point at infinity). Its
reprojection into keyframe ``j`` is ``pi(K, (T_j^-1 T_i X_i)[:3])`` with ``T = world_from_cam``.

Jacobians (all analytic, checked against ``torch.func.jacfwd`` in tests) are with respect to

* the left tangent ``xi_i``/``xi_j`` of ``T_i``/``T_j`` (see :mod:`services.ba.core.se3`: ``T <- exp(xi) T``,
  ``xi = (rho, phi)``). With this convention ``J_pose_j = -J_pose_i`` exactly;
* the disparity ``d`` of the source pixel;
* the **focal length** ``fx``, with the aspect ``fy / fx`` held (the working resize may scale x and y a little
  differently);
* when asked, the **principal point** ``(cx, cy)``: a lens's centre is off the image centre by up to a few
  percent (KITTI 07: 10.6 px of 1226), and BA that holds it at the centre bends the trajectory instead.

Coordinates are pixels of whatever image the intrinsics belong to (in BA: the 1/8 grid, see
docs/CONVENTIONS.md).
"""
from __future__ import annotations

from typing import NamedTuple

import torch

from services.ba.core.projective_numpy import MIN_DEPTH  # one threshold for both layouts


class Reprojection(NamedTuple):
    """Reprojection of source pixels into target keyframes, per edge ``e`` and pixel ``p``."""

    coords: torch.Tensor  # (E, P, 2) pixel (x, y) in keyframe j
    valid: torch.Tensor  # (E, P) bool: in front of camera j (does not check the image bounds)
    j_pose_focal: torch.Tensor | None  # (E, P, 2, 7 or 9) d coords / d [xi_i, f(, cx, cy)] (one buffer, see the
    # views below)
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
        """``(E, P, 2)`` d coords / d fx (fy / fx held)."""
        return self.j_pose_focal[..., 6]

    @property
    def j_principal(self) -> torch.Tensor | None:
        """``(E, P, 2, 2)`` d coords / d (cx, cy), or None when they were not asked for."""
        return self.j_pose_focal[..., 7:9] if self.j_pose_focal.shape[-1] == 9 else None


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
              pixels: torch.Tensor, intrinsics: torch.Tensor, with_jacobians: bool = True,
              principal_point: bool = False) -> Reprojection:
    """Reproject source pixels of keyframe ``i`` with their disparities into keyframe ``j``, per edge.

    Args:
        world_from_cam_i: ``(E, 4, 4)`` source poses.
        world_from_cam_j: ``(E, 4, 4)`` target poses.
        disparity: ``(E, P)`` source disparities (inverse depth); the per-pixel work runs in its dtype.
        pixels: ``(P, 2)`` source pixel coordinates ``(x, y)``.
        intrinsics: ``(4,)`` ``(fx, fy, cx, cy)``; the focal Jacobian is with respect to ``fx`` with the aspect
            ``fy / fx`` held (a resize to the working size scales x and y differently; one focal for both biased
            KITTI's by +2.3 %).
        with_jacobians: also return the analytic Jacobians.
        principal_point: the Jacobians include d coords / d (cx, cy) (``j_principal``).
    Returns:
        :class:`Reprojection` (Jacobian fields ``None`` when ``with_jacobians`` is false); the tensors are
        views of the channels-first :class:`PlaneReprojection` of :func:`reproject_planes`.
    """
    out = reproject_planes(world_from_cam_i, world_from_cam_j, disparity, pixels, intrinsics, with_jacobians,
                           principal_point)
    if not with_jacobians:
        return Reprojection(out.coords.transpose(1, 2), out.valid, None, None)
    return Reprojection(out.coords.transpose(1, 2), out.valid, out.jac.permute(0, 3, 2, 1),
                        out.j_disp.transpose(1, 2))


class PlaneReprojection(NamedTuple):
    """:class:`Reprojection` with the pixel index last (``P`` contiguous): the layout dense BA works in."""

    coords: torch.Tensor  # (E, 2, P) pixel (x, y) in keyframe j
    valid: torch.Tensor  # (E, P) bool: in front of camera j
    jac: torch.Tensor | None  # (E, 7 or 9, 2, P) d coords / d [xi_i, f(, cx, cy)]; d / d xi_j is minus the first 6
    j_disp: torch.Tensor | None  # (E, 2, P) d coords / d disparity of the source pixel


def reproject_planes(world_from_cam_i: torch.Tensor, world_from_cam_j: torch.Tensor, disparity: torch.Tensor,
                     pixels: torch.Tensor, intrinsics: torch.Tensor, with_jacobians: bool = True,
                     principal_point: bool = False) -> PlaneReprojection:
    """:func:`reproject` in the channels-first layout; per-edge rigid motions are formed in the pose dtype,
    per-pixel arithmetic runs in ``disparity.dtype`` (float32 halves the memory traffic of dense BA)."""
    n_edges, n_pix = disparity.shape
    if world_from_cam_i.shape != (n_edges, 4, 4) or world_from_cam_j.shape != (n_edges, 4, 4):
        raise ValueError(f"poses must be ({n_edges}, 4, 4), got {world_from_cam_i.shape}, {world_from_cam_j.shape}")
    if pixels.shape != (n_pix, 2):
        raise ValueError(f"pixels must be ({n_pix}, 2), got {tuple(pixels.shape)}")
    dtype = disparity.dtype
    rot_i, rot_j = world_from_cam_i[:, :3, :3], world_from_cam_j[:, :3, :3]
    baseline = world_from_cam_i[:, :3, 3] - world_from_cam_j[:, :3, 3]  # (E, 3) world frame
    rot_ji = (rot_j.transpose(1, 2) @ rot_i).to(dtype)  # camera i -> camera j
    t_ji = (rot_j.transpose(1, 2) @ baseline[..., None]).to(dtype)  # (E, 3, 1)
    intr = intrinsics.to(dtype)
    fx, fy, cx, cy = intr.unbind(-1)
    pix = pixels.to(dtype)
    q = torch.stack([(pix[:, 0] - cx) / fx, (pix[:, 1] - cy) / fy, torch.ones_like(pix[:, 0])])  # (3, P)
    d = disparity[:, None, :]  # (E, 1, P)
    rq = rot_ji @ q  # (E, 3, P)
    x_j = rq + t_ji * d  # camera-j point scaled by d
    z = x_j[:, 2]
    valid = z > MIN_DEPTH * disparity
    inv_z = 1 / torch.where(z.abs() < 1e-12, torch.full_like(z, 1e-12), z)
    u_n, v_n = x_j[:, 0] * inv_z, x_j[:, 1] * inv_z
    coords = torch.stack([fx * u_n + cx, fy * v_n + cy], 1)
    if not with_jacobians:
        return PlaneReprojection(coords, valid, None, None)

    # a_r = (row r of d pi / d x_j) R_j^T: derivative of pixel coordinate r w.r.t. the (scaled) world point
    cols = rot_j.to(dtype)[..., None]  # (E, 3, 3, 1): cols[:, :, k] is column k of R_j
    gx, gy = (fx * inv_z)[:, None], (fy * inv_z)[:, None]  # (E, 1, P)
    a = torch.stack([gx * (cols[:, :, 0] - u_n[:, None] * cols[:, :, 2]),
                     gy * (cols[:, :, 1] - v_n[:, None] * cols[:, :, 2])], 2)  # (E, 3, 2, P)
    p_w = (rot_i.to(dtype) @ q + world_from_cam_i[:, :3, 3, None].to(dtype) * d)[:, :, None]  # (E, 3, 1, P)
    jac = torch.empty(n_edges, 9 if principal_point else 7, 2, n_pix, dtype=dtype, device=disparity.device)
    # the left tangent of T_i moves the world point by [d I, -[p_w]x] xi; a^T (-[p_w]x) is the row (p_w x a)^T
    torch.mul(a, d[:, :, None], out=jac[:, :3])
    jac[:, 3] = p_w[:, 1] * a[:, 2] - p_w[:, 2] * a[:, 1]
    jac[:, 4] = p_w[:, 2] * a[:, 0] - p_w[:, 0] * a[:, 2]
    jac[:, 5] = p_w[:, 0] * a[:, 1] - p_w[:, 1] * a[:, 0]
    j_disp = (a * baseline.to(dtype)[:, :, None, None]).sum(1)  # (E, 2, P)
    # fx enters through q = ((x - cx)/fx, (y - cy)/(a fx), 1) with the aspect a = fy/fx held:
    # d x_j / d fx = -(R_ji q - R_ji e_z) / fx, and the projection's fy = a fx scales with it
    dx_df = (rot_ji[:, :, 2:3] - rq) / fx  # (E, 3, P)
    jac[:, 6, 0] = u_n + gx[:, 0] * (dx_df[:, 0] - u_n * dx_df[:, 2])
    jac[:, 6, 1] = (fy / fx) * v_n + gy[:, 0] * (dx_df[:, 1] - v_n * dx_df[:, 2])
    if principal_point:
        # (cx, cy) enter q as -(cx / fx, cy / fy) and the projection as + (cx, cy): d x_j / d cx = -R_ji e_x / fx
        for k, (axis, f) in enumerate(((0, fx), (1, fy))):
            dx = (-rot_ji[:, :, axis] / f)[..., None]  # (E, 3, 1)
            jac[:, 7 + k, 0] = gx[:, 0] * (dx[:, 0] - u_n * dx[:, 2]) + (axis == 0)
            jac[:, 7 + k, 1] = gy[:, 0] * (dx[:, 1] - v_n * dx[:, 2]) + (axis == 1)
    return PlaneReprojection(coords, valid, jac, j_disp)
