"""Reprojection of keyframe grid pixels into one camera, with the derivative by that camera's pose, on numpy:
what motion-only alignment and DIS's initial flows need, for the tracking process, which runs without torch.

The same model and conventions as :mod:`services.ba.core.projective` (inverse-depth points, ``world_from_cam``
poses, left updates); tests check both give the same coordinates and Jacobians, and that one against autograd.
"""
from __future__ import annotations

from typing import NamedTuple

import cv2
import numpy as np

from services.ba.core.host_arrays import as_numpy


# Points closer than this depth (units of 1/disparity) in the target camera are marked invalid.
MIN_DEPTH = 1e-3


class CameraReprojection(NamedTuple):
    """``M`` source keyframes' pixels reprojected into one camera."""

    coords: np.ndarray  # (M, P, 2) pixel (x, y) in the camera
    valid: np.ndarray  # (M, P) bool: in front of the camera (image bounds not checked)
    jac_rows: np.ndarray | None  # (6, M, 2, P) d coords / d xi of the camera (left tangent of its world_from_cam),
    # one contiguous row per tangent direction: the layout a 6x6 normal matrix is summed from (motion.align)

    @property
    def j_pose(self) -> np.ndarray | None:
        """The Jacobian as ``(M, P, 2, 6)``, :mod:`services.ba.core.projective`'s layout (a view)."""
        return None if self.jac_rows is None else self.jac_rows.transpose(1, 3, 2, 0)


def pixel_grid(height: int, width: int) -> np.ndarray:
    """Pixel centres ``(height*width, 2)`` float64 as ``(x, y)``, row-major (docs/CONVENTIONS.md)."""
    rows, cols = np.meshgrid(np.arange(height, dtype=np.float64), np.arange(width, dtype=np.float64), indexing="ij")
    return np.stack([cols, rows], axis=-1).reshape(-1, 2)


def reproject_into(source_poses: np.ndarray, pose: np.ndarray, disparity: np.ndarray, pixels: np.ndarray,
                   intrinsics: np.ndarray, with_jacobian: bool = True) -> CameraReprojection:
    """Pixels of ``M`` keyframes (``source_poses`` ``(M, 4, 4)``, ``disparity`` ``(M, P)`` at ``pixels``
    ``(P, 2)``) reprojected into the camera ``pose`` ``(4, 4)``; ``intrinsics`` ``(4,)`` shared. float64."""
    m, n_pix = disparity.shape
    if source_poses.shape != (m, 4, 4) or pose.shape != (4, 4) or pixels.shape != (n_pix, 2):
        raise ValueError(f"source_poses ({m},4,4), pose (4,4) and pixels ({n_pix},2) expected, got "
                         f"{source_poses.shape}, {pose.shape}, {pixels.shape}")
    fx, fy, cx, cy = (float(v) for v in intrinsics)
    rot_j = pose[:3, :3]
    rot_i, trans_i = source_poses[:, :3, :3], source_poses[:, :3, 3]
    rot_ji = rot_j.T[None] @ rot_i  # (M, 3, 3) camera i -> the camera
    t_ji = (trans_i - pose[:3, 3]) @ rot_j  # (M, 3): R_j^T (t_i - t_j)
    q = np.stack([(pixels[:, 0] - cx) / fx, (pixels[:, 1] - cy) / fy, np.ones(n_pix)])  # (3, P)
    x = rot_ji @ q + t_ji[:, :, None] * disparity[:, None, :]  # (M, 3, P): the point scaled by its disparity
    z = x[:, 2]
    valid = z > MIN_DEPTH * disparity
    inv_z = 1 / np.where(np.abs(z) < 1e-12, 1e-12, z)
    u_n, v_n = x[:, 0] * inv_z, x[:, 1] * inv_z
    coords = np.stack([fx * u_n + cx, fy * v_n + cy], axis=-1)
    if not with_jacobian:
        return CameraReprojection(coords, valid, None)
    # a_c[:, r]: d pixel coordinate r / d world coordinate c of the scaled point; the camera's left tangent moves
    # that point (relative to the camera) by -[d I, -[p_w]x] xi (services.ba.core.projective, with J_j = -J_i).
    # Built a tangent direction at a time on (M, 2, P) arrays: the (M, P, 2, 6) layout's strided writes made one
    # alignment ~20 % slower (docs/BENCHMARKS.md)
    gx, gy = fx * inv_z, fy * inv_z  # (M, P)
    a = [np.stack([gx * (rot_j[c, 0] - u_n * rot_j[c, 2]), gy * (rot_j[c, 1] - v_n * rot_j[c, 2])], axis=1)
         for c in range(3)]  # (M, 2, P) each
    p_w = rot_i @ q + trans_i[:, :, None] * disparity[:, None, :]  # (M, 3, P)
    p = [p_w[:, c, None, :] for c in range(3)]  # (M, 1, P) each
    minus_d = -disparity[:, None, :]
    jac = np.empty((6, m, 2, n_pix))
    for c in range(3):
        np.multiply(a[c], minus_d, out=jac[c])
    jac[3] = p[2] * a[1] - p[1] * a[2]
    jac[4] = p[0] * a[2] - p[2] * a[0]
    jac[5] = p[1] * a[0] - p[0] * a[1]
    return CameraReprojection(coords, valid, jac)


def induced_flow_field(pose_i, pose_j, disparity_i, intrinsics, grid: int) -> np.ndarray:
    """Working-resolution flow ``(h*grid, w*grid, 2)`` float32 of keyframe i into camera j that the poses
    (``(4, 4)`` world_from_cam) and i's grid disparity ``(h, w)`` induce (0 where a point falls behind camera j):
    an initial flow for DIS. Arguments are numpy arrays or torch tensors (mapping's graph)."""
    disparity_i = as_numpy(disparity_i)
    h, w = disparity_i.shape
    pixels = pixel_grid(h, w)
    rp = reproject_into(as_numpy(pose_i)[None], as_numpy(pose_j), disparity_i.reshape(1, -1), pixels,
                        as_numpy(intrinsics), with_jacobian=False)
    flow = ((rp.coords[0] - pixels) * rp.valid[0, :, None] * grid).reshape(h, w, 2)
    flow = np.nan_to_num(flow, nan=0.0, posinf=0.0, neginf=0.0).astype(np.float32)
    # grid cell centres sit at working pixels 8c + 3.5, so a plain resize keeps them aligned
    return cv2.resize(flow, (w * grid, h * grid), interpolation=cv2.INTER_LINEAR)


def translational_parallax(pose_i, pose_j, disparity_i, intrinsics) -> float:
    """Median distance (grid px) between where keyframe i's grid points land in camera j and where they would land
    were camera j turned the same but at camera i's centre: the parallax j's translation makes, the part of a flow
    that carries depth and translation. Poses ``(4, 4)`` world_from_cam, ``disparity_i`` ``(h, w)``, ``intrinsics``
    ``(4,)`` of the grid (numpy arrays or torch tensors); 0 where no point lands in front of both."""
    disparity_i, intrinsics = as_numpy(disparity_i), as_numpy(intrinsics)
    pixels = pixel_grid(*disparity_i.shape)
    source, pose_j = as_numpy(pose_i)[None], as_numpy(pose_j)
    turned = pose_j.copy()
    turned[:3, 3] = source[0, :3, 3]
    moved, still = (reproject_into(source, pose, disparity_i.reshape(1, -1), pixels, intrinsics, with_jacobian=False)
                    for pose in (pose_j, turned))
    valid = moved.valid[0] & still.valid[0]
    if not valid.any():
        return 0.0
    return float(np.median(np.linalg.norm(moved.coords[0] - still.coords[0], axis=1)[valid]))
