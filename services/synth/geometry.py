"""Ground-truth geometry helpers: back-projection, projection and exact static-scene correspondence.

Conventions (docs/CONVENTIONS.md): world_from_cam (4, 4) float64, OpenCV camera (x right, y down, z forward),
intrinsics (fx, fy, cx, cy), pixel (row r, column c) has its centre at u = c, v = r; depth = camera z.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np


def _check_intrinsics(intrinsics: np.ndarray) -> np.ndarray:
    intr = np.asarray(intrinsics, np.float64)
    if intr.shape != (4,):
        raise ValueError(f"intrinsics must be (4,) (fx, fy, cx, cy), got shape {intr.shape}")
    return intr


def _check_pose(pose: np.ndarray, name: str) -> np.ndarray:
    pose = np.asarray(pose, np.float64)
    if pose.shape != (4, 4):
        raise ValueError(f"{name} must be (4, 4), got shape {pose.shape}")
    return pose


def pixel_grid(height: int, width: int) -> np.ndarray:
    """Pixel centres (H, W, 2) float64 as (u, v) = (column, row)."""
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    return np.stack([u, v], axis=-1)


def backproject(depth: np.ndarray, intrinsics: np.ndarray, world_from_cam: np.ndarray) -> np.ndarray:
    """World points (H, W, 3) float64 metres of every pixel of a depth map (H, W) metres (camera z)."""
    depth = np.asarray(depth, np.float64)
    if depth.ndim != 2:
        raise ValueError(f"depth must be (H, W), got shape {depth.shape}")
    fx, fy, cx, cy = _check_intrinsics(intrinsics)
    pose = _check_pose(world_from_cam, "world_from_cam")
    uv = pixel_grid(*depth.shape)
    cam = np.stack([(uv[..., 0] - cx) / fx * depth, (uv[..., 1] - cy) / fy * depth, depth], axis=-1)
    return cam @ pose[:3, :3].T + pose[:3, 3]


class Projection(NamedTuple):
    """Pixels of world points in a camera."""

    uv: np.ndarray  # (..., 2) float64 pixel coordinates (u = column, v = row)
    z: np.ndarray  # (...,) float64 depth (camera z), metres; <= 0 means behind the camera


def project(points_world: np.ndarray, intrinsics: np.ndarray, world_from_cam: np.ndarray) -> Projection:
    """Project world points (..., 3) metres into the camera ``world_from_cam`` (4, 4)."""
    pts = np.asarray(points_world, np.float64)
    if pts.shape[-1] != 3:
        raise ValueError(f"points_world must be (..., 3), got shape {pts.shape}")
    fx, fy, cx, cy = _check_intrinsics(intrinsics)
    cam_from_world = np.linalg.inv(_check_pose(world_from_cam, "world_from_cam"))
    cam = pts @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
    z = cam[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = np.stack([fx * cam[..., 0] / z + cx, fy * cam[..., 1] / z + cy], axis=-1)
    return Projection(uv, z)


class Correspondence(NamedTuple):
    """Where each pixel of frame i lands in frame j, for a static scene."""

    uv: np.ndarray  # (H, W, 2) float64 pixel coordinates in frame j
    flow: np.ndarray  # (H, W, 2) float64 uv - pixel_grid: optical flow i -> j, pixels (du, dv)
    z: np.ndarray  # (H, W) float64 depth of the point in frame j (camera z), metres
    in_view: np.ndarray  # (H, W) bool: in front of camera j and inside its image


def static_correspondence(depth_i: np.ndarray, intrinsics: np.ndarray, world_from_cam_i: np.ndarray,
                          world_from_cam_j: np.ndarray) -> Correspondence:
    """Exact correspondence i -> j from frame i's depth (H, W) metres and both poses (static scene).

    Occlusion is not decided here: compare ``z`` with frame j's depth at ``uv`` (see :func:`visible_in_j`).
    """
    points = backproject(depth_i, intrinsics, world_from_cam_i)
    proj = project(points, intrinsics, world_from_cam_j)
    h, w = np.shape(depth_i)
    u, v = proj.uv[..., 0], proj.uv[..., 1]
    in_view = (proj.z > 0) & (u >= -0.5) & (u <= w - 0.5) & (v >= -0.5) & (v <= h - 0.5)
    return Correspondence(proj.uv, proj.uv - pixel_grid(h, w), proj.z, in_view)


def sample_bilinear(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``image`` (H, W) at ``uv`` (..., 2) pixels; coordinates clamped to the image."""
    h, w = image.shape
    u = np.clip(uv[..., 0], 0, w - 1)
    v = np.clip(uv[..., 1], 0, h - 1)
    u0 = np.minimum(np.floor(u).astype(np.int64), w - 2) if w > 1 else np.zeros(u.shape, np.int64)
    v0 = np.minimum(np.floor(v).astype(np.int64), h - 2) if h > 1 else np.zeros(v.shape, np.int64)
    au, av = u - u0, v - v0
    u1, v1 = np.minimum(u0 + 1, w - 1), np.minimum(v0 + 1, h - 1)
    top = image[v0, u0] * (1 - au) + image[v0, u1] * au
    return top * (1 - av) + (image[v1, u0] * (1 - au) + image[v1, u1] * au) * av


def visible_in_j(corr: Correspondence, depth_j: np.ndarray, rel_tol: float = 1e-3) -> np.ndarray:
    """(H, W) bool: the point of pixel i is in view in frame j and not occluded there.

    Compares inverse depths, which are exactly bilinear across a planar surface, so the test is tight away
    from depth edges; ``rel_tol`` is the accepted relative difference of inverse depth.
    """
    inv_j = sample_bilinear(1.0 / np.asarray(depth_j, np.float64), corr.uv)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_z = 1.0 / corr.z
        return corr.in_view & (np.abs(inv_z - inv_j) <= rel_tol * inv_j)
