"""Depth prior as disparity (1/m) on the 1/8 grid: from sensor depth, from a metric depth model, or none.

0 marks unknown cells (docs/CONVENTIONS.md). BA regularises disparities towards the prior where it exists
and runs scale-free when there is none.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from .geometry import GRID_STRIDE
from .resample import resize_bilinear

DepthModel = Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True)
class DepthParams:
    min_depth_m: float = 0.1
    """Depths below this are treated as invalid (sensor noise, model artefacts)."""
    max_depth_m: float = 80.0
    """Depths above this are treated as unknown (sky, out of range)."""
    model_short_side: int = 266
    """Shorter side of the image fed to the depth model (rounded to its patch size); larger is slower."""
    min_valid_fraction: float = 0.5
    """A grid cell needs this fraction of valid sensor pixels to get a disparity."""


def _cell_mean_disparity(depth_m: np.ndarray, grid_hw: tuple[int, int], params: DepthParams) -> np.ndarray:
    """(H, W) depth at working resolution → (h, w) mean inverse depth of the valid pixels of each 8×8 cell."""
    valid = (depth_m >= params.min_depth_m) & (depth_m <= params.max_depth_m)
    inv = np.where(valid, 1.0 / np.maximum(depth_m, 1e-6), 0.0).astype(np.float32)
    h, w = grid_hw
    s = GRID_STRIDE
    inv_sum = inv.reshape(h, s, w, s).sum(axis=(1, 3))
    count = valid.reshape(h, s, w, s).sum(axis=(1, 3)).astype(np.float32)
    out = np.where(count >= params.min_valid_fraction * s * s, inv_sum / np.maximum(count, 1.0), 0.0)
    return out.astype(np.float32)


def sensor_disparity(depth_m: np.ndarray, working_hw: tuple[int, int], params: DepthParams = DepthParams()) -> np.ndarray:
    """Sensor depth (H0, W0) float32 metres (0 = missing), any resolution → (H/8, W/8) float32 disparity.

    Resampled to the working size with nearest neighbour (never blends a valid depth with a hole), then
    averaged in inverse depth per grid cell.
    """
    import cv2

    if depth_m.ndim != 2:
        raise ValueError(f"sensor depth must be (H, W), got {depth_m.shape}")
    H, W = working_hw
    if H % GRID_STRIDE or W % GRID_STRIDE:
        raise ValueError(f"working size must be multiples of {GRID_STRIDE}, got {working_hw}")
    d = cv2.resize(depth_m.astype(np.float32), (W, H), interpolation=cv2.INTER_NEAREST)
    return _cell_mean_disparity(d, (H // GRID_STRIDE, W // GRID_STRIDE), params)


def model_disparity(
    image: np.ndarray, depth_model: DepthModel, patch_size: int, params: DepthParams = DepthParams()
) -> np.ndarray:
    """Metric depth model on (1, 3, H, W) normalised working image → (H/8, W/8) float32 disparity (1/m)."""
    if image.ndim != 4 or image.shape[:2] != (1, 3):
        raise ValueError(f"image must be (1, 3, H, W), got {tuple(image.shape)}")
    H, W = image.shape[2:]
    s = params.model_short_side / min(H, W)
    size = (max(patch_size, round(H * s / patch_size) * patch_size), max(patch_size, round(W * s / patch_size) * patch_size))
    x = resize_bilinear(image, size, antialias=s < 1.0)
    depth = resize_bilinear(np.asarray(depth_model(x), np.float32)[0], (H, W))
    return _cell_mean_disparity(depth, (H // GRID_STRIDE, W // GRID_STRIDE), params)
