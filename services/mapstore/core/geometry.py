"""Grid geometry: intrinsics on the 1/8 grid, back-projection, projection, colour sampling.

Conventions (docs/CONVENTIONS.md): pixel centres at integer coordinates, camera x right / y down /
z forward, disparity = 1/depth with 0 = unknown, poses are `world_from_cam` 4×4 float64.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from services.common.camera import scale_intrinsics

GRID_STRIDE = 8
"""Working-resolution pixels per grid cell side."""


class Projection(NamedTuple):
    """Points projected into a camera. All arrays have length N."""

    u: np.ndarray  # (N,) float64, column coordinate in pixels of that camera's image/grid
    v: np.ndarray  # (N,) float64, row coordinate
    z: np.ndarray  # (N,) float64, depth (camera z); ≤ 0 means behind the camera


def _check_intrinsics(intrinsics: np.ndarray) -> np.ndarray:
    k = np.asarray(intrinsics, dtype=np.float64)
    if k.shape != (4,):
        raise ValueError(f"intrinsics must be (4,) = (fx, fy, cx, cy), got shape {k.shape}")
    return k


def grid_intrinsics(intrinsics: np.ndarray, stride: int = GRID_STRIDE) -> np.ndarray:
    """Intrinsics of the 1/stride grid from working-resolution intrinsics.

    Args:
        intrinsics: (4,) float64 (fx, fy, cx, cy) in working-resolution pixels.
        stride: grid cell side in pixels (8).
    Returns:
        (4,) float64 (fx/s, fy/s, (cx+0.5)/s − 0.5, (cy+0.5)/s − 0.5).
    """
    _check_intrinsics(intrinsics)
    return scale_intrinsics(intrinsics, 1 / stride, 1 / stride)


def backproject_grid(disparity: np.ndarray, grid_k: np.ndarray) -> np.ndarray:
    """Camera-frame points of every grid cell.

    Args:
        disparity: (h, w) float, inverse depth per cell; cells ≤ 0 give non-finite points
            (callers mask them out first).
        grid_k: (4,) float64 grid intrinsics (fx, fy, cx, cy).
    Returns:
        (h, w, 3) float64 points in the keyframe's camera frame (same units as 1/disparity).
    """
    if disparity.ndim != 2:
        raise ValueError(f"disparity must be (h, w), got shape {disparity.shape}")
    fx, fy, cx, cy = _check_intrinsics(grid_k)
    h, w = disparity.shape
    with np.errstate(divide="ignore"):
        z = 1.0 / disparity.astype(np.float64)
    v, u = np.meshgrid(np.arange(h, dtype=np.float64), np.arange(w, dtype=np.float64), indexing="ij")
    return np.stack([(u - cx) / fx * z, (v - cy) / fy * z, z], axis=-1)


def transform_points(a_from_b: np.ndarray, points_b: np.ndarray) -> np.ndarray:
    """Apply a 4×4 rigid transform to points.

    Args:
        a_from_b: (4, 4) float64 homogeneous transform.
        points_b: (N, 3) float points in frame b.
    Returns:
        (N, 3) float64 points in frame a.
    """
    if a_from_b.shape != (4, 4):
        raise ValueError(f"transform must be (4, 4), got {a_from_b.shape}")
    if points_b.ndim != 2 or points_b.shape[1] != 3:
        raise ValueError(f"points must be (N, 3), got {points_b.shape}")
    return points_b.astype(np.float64) @ a_from_b[:3, :3].T + a_from_b[:3, 3]


def project(points_cam: np.ndarray, k: np.ndarray) -> Projection:
    """Pinhole projection of camera-frame points.

    Args:
        points_cam: (N, 3) float points in the camera frame.
        k: (4,) float64 intrinsics of the target image (or grid).
    Returns:
        Projection with u, v (pixels, centres at integers) and z; u, v are NaN where z ≤ 0.
    """
    fx, fy, cx, cy = _check_intrinsics(k)
    z = points_cam[:, 2].astype(np.float64)
    safe = np.where(z > 0, z, np.nan)
    return Projection(points_cam[:, 0] / safe * fx + cx, points_cam[:, 1] / safe * fy + cy, z)


def sample_cell_colours(image: np.ndarray, stride: int = GRID_STRIDE) -> np.ndarray:
    """Colour of each grid cell, bilinearly sampled at the cell centre.

    Cell (r, c) has its centre at pixel (stride·c + (stride−1)/2, stride·r + (stride−1)/2); for an
    even stride that is the mean of the 2×2 central pixels.

    Args:
        image: (H, W, 3) uint8 RGB working-resolution image, H and W multiples of `stride`.
    Returns:
        (H/stride, W/stride, 3) uint8 RGB.
    """
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"image must be (H, W, 3), got {image.shape}")
    h, w = image.shape[:2]
    if h % stride or w % stride:
        raise ValueError(f"image sides {h}x{w} must be multiples of {stride}")
    lo, hi = (stride - 1) // 2, stride // 2
    img = image.astype(np.float32)
    acc = img[lo::stride, lo::stride] + img[lo::stride, hi::stride]
    acc += img[hi::stride, lo::stride] + img[hi::stride, hi::stride]
    return np.clip(np.rint(acc / 4.0), 0, 255).astype(np.uint8)
