"""Rotation-only geometry of dense flow: the rotation that best explains a flow field, and the flow it leaves.

A camera that only rotates moves every pixel as if the scene were at infinity; its translation (parallax) is what
remains after the best rotation is taken out. Monocular SLAM needs that parallax to start a map, and has none to
estimate while the camera turns on the spot.
"""
from __future__ import annotations

import numpy as np


def _bearings(x_grid: np.ndarray, y_grid: np.ndarray, intrinsics: np.ndarray, grid: int) -> np.ndarray:
    """Unit rays (M, 3) of grid coordinates, for images whose cells are ``grid`` pixels with ``intrinsics``."""
    fx, fy, cx, cy = (float(v) for v in intrinsics)
    x, y = (x_grid + 0.5) * grid - 0.5, (y_grid + 0.5) * grid - 0.5  # grid -> pixels of these images
    rays = np.stack([(x - cx) / fx, (y - cy) / fy, np.ones_like(x)], -1).reshape(-1, 3)
    return rays / np.linalg.norm(rays, axis=1, keepdims=True)


def bearing_rotation(target: np.ndarray, confidence: np.ndarray, intrinsics: np.ndarray, grid: int,
                     min_confidence: float = 0.5) -> np.ndarray:
    """(3, 3) rotation ``R`` (cam_b_from_cam_a) that best maps the bearings of camera a's grid cells onto those of
    their flow ``target`` in camera b (Kabsch / Wahba), as if the scene were at infinity. ``target``: (h, w, 2)
    grid coordinates in b; ``confidence``: (h, w); ``intrinsics``: (4,) of the images the flow ran on, whose
    cells are ``grid`` pixels. Cells below ``min_confidence`` are left out, then the worst fifth of the rest
    (parallax, moving objects) and the rotation fitted again. Identity without evidence."""
    h, w = confidence.shape
    rows, cols = np.mgrid[0:h, 0:w]
    a = _bearings(cols.astype(np.float64), rows.astype(np.float64), intrinsics, grid)
    b = _bearings(target[..., 0].astype(np.float64), target[..., 1].astype(np.float64), intrinsics, grid)
    weight = np.where(confidence.reshape(-1) >= min_confidence, confidence.reshape(-1), 0.0)
    rot = np.eye(3)
    for _ in range(2):
        if weight.sum() < 10:
            return np.eye(3)
        u, _, vt = np.linalg.svd((b * weight[:, None]).T @ a)
        rot = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
        residual = np.linalg.norm(b - a @ rot.T, axis=1)
        keep = weight > 0
        weight = np.where(residual <= np.quantile(residual[keep], 0.8), weight, 0.0) if keep.any() else weight
    return rot


def parallax_after_rotation(target: np.ndarray, confidence: np.ndarray, intrinsics: np.ndarray, grid: int,
                            min_confidence: float = 0.5) -> float:
    """Mean distance (grid px) between where a's confident cells land (``target``, (h, w, 2) grid coordinates in b)
    and where the best rotation alone (:func:`bearing_rotation`) would put them: the flow translation causes.
    ``intrinsics``: (4,) of images whose cells are ``grid`` pixels. 0 without evidence."""
    h, w = confidence.shape
    keep = confidence.reshape(-1) >= min_confidence
    if keep.sum() < 10:
        return 0.0
    rot = bearing_rotation(target, confidence, intrinsics, grid, min_confidence)
    rows, cols = np.mgrid[0:h, 0:w]
    turned = _bearings(cols.astype(np.float64), rows.astype(np.float64), intrinsics, grid) @ rot.T
    fx, fy, cx, cy = (float(v) for v in intrinsics)
    z = np.clip(turned[:, 2], 1e-6, None)
    x = (fx * turned[:, 0] / z + cx + 0.5) / grid - 0.5
    y = (fy * turned[:, 1] / z + cy + 0.5) / grid - 0.5
    gap = np.hypot(target.reshape(-1, 2)[:, 0] - x, target.reshape(-1, 2)[:, 1] - y)
    front = turned[:, 2] > 1e-3
    return float(gap[keep & front].mean()) if (keep & front).any() else 0.0


def flow_noise(confidence: np.ndarray, fb_sigma_grid: float, min_confidence: float = 0.5) -> float:
    """Mean forward-backward error (grid px) of the confident cells, recovered from their confidence
    ``exp(-e^2 / (2 sigma^2))`` (``fb_sigma_grid``: sigma in grid px): the noise a flow field measures itself with.
    0 without confident cells."""
    conf = confidence.reshape(-1)
    conf = conf[conf >= min_confidence]
    if conf.size == 0:
        return 0.0
    return float((np.sqrt(-2.0 * np.log(np.clip(conf, 1e-12, 1.0))) * fb_sigma_grid).mean())


def translates(target: np.ndarray, confidence: np.ndarray, intrinsics: np.ndarray, grid: int, fb_sigma_grid: float,
               min_ratio: float, min_confidence: float = 0.5) -> bool | None:
    """Whether a flow field shows translation: the flow the best rotation leaves (:func:`parallax_after_rotation`)
    is above ``min_ratio`` x the flow's own forward-backward noise (:func:`flow_noise`). An absolute threshold
    would be the synthetic DIS noise (rotation leaves 0.006 grid px, a hand-held walk 0.04 per frame) or a real
    camera's, not both; the ratio is 0.6-0.7 for a pure rotation, 2.3-2.9 for a 4 deg/frame pan that moves
    0.5 cm/frame, 5 and more for walking. None when too few cells are confident to tell (flow that broke: a
    turn too far for DIS leaves about 2 % of the cells)."""
    if (confidence >= min_confidence).mean() < 0.5:
        return None
    parallax = parallax_after_rotation(target, confidence, intrinsics, grid, min_confidence)
    return parallax > min_ratio * flow_noise(confidence, fb_sigma_grid, min_confidence)
