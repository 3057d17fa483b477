"""Query by example: a region of an image → one feature vector in the backbone's space.

The backbone gives a (C, h, w) patch-feature map of the image; the region (a pixel box or a mask) is
area-averaged onto the patch grid, and the patch features are averaged with those weights.
"""
from __future__ import annotations

import cv2
import numpy as np


def box_mask(height: int, width: int, box: tuple[float, float, float, float]) -> np.ndarray:
    """(H, W) bool mask of the pixels whose centres lie in ``box = (x0, y0, x1, y1)`` (pixels, x1/y1 exclusive).

    Raises ValueError when the box is empty or outside the image.
    """
    x0, y0, x1, y1 = (float(v) for v in box)
    cols, rows = np.arange(width), np.arange(height)
    inside_x = (cols >= x0) & (cols < x1)
    inside_y = (rows >= y0) & (rows < y1)
    mask = inside_y[:, None] & inside_x[None, :]
    if not mask.any():
        raise ValueError(f"box {box} covers no pixel of the {width}x{height} image")
    return mask


def _adaptive_mean(n_in: int, n_out: int) -> np.ndarray:
    """(n_out, n_in) weights of adaptive average pooling along one axis: bin i averages the inputs
    [⌊i·n_in/n_out⌋, ⌈(i+1)·n_in/n_out⌉), as torch's ``adaptive_avg_pool2d``."""
    weights = np.zeros((n_out, n_in), np.float64)
    for i in range(n_out):
        start, end = (i * n_in) // n_out, -((-(i + 1) * n_in) // n_out)
        weights[i, start:end] = 1.0 / (end - start)
    return weights


def pooled_feature(feature_map: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(C, h, w) float features + (H, W) bool mask → (C,) float32 unit vector (mask-weighted mean)."""
    feature_map = np.asarray(feature_map, np.float32)
    if feature_map.ndim != 3:
        raise ValueError(f"feature_map must be (C, h, w), got {tuple(feature_map.shape)}")
    mask = np.asarray(mask, bool)
    if mask.ndim != 2 or not mask.any():
        raise ValueError("mask must be a non-empty (H, W) boolean array")
    (h, w), (H, W) = feature_map.shape[1:], mask.shape
    weights = _adaptive_mean(H, h) @ mask.astype(np.float64) @ _adaptive_mean(W, w).T  # (h, w) area fractions
    if float(weights.sum()) <= 0:
        raise ValueError("mask covers no patch")
    vec = np.tensordot(feature_map, weights, axes=([1, 2], [0, 1])) / weights.sum()
    return (vec / max(float(np.linalg.norm(vec)), 1e-12)).astype(np.float32)


def fit_to_patches(image: np.ndarray, mask: np.ndarray, patch: int, max_side: int) -> tuple[np.ndarray, np.ndarray]:
    """Resize image (H, W, 3) uint8 and mask (H, W) bool so both sides are multiples of ``patch`` and the long
    side is at most ``max_side`` (aspect kept up to rounding). Returns (image, mask) resized."""
    h, w = image.shape[:2]
    scale = min(1.0, max_side / max(h, w))
    nh, nw = (max(patch, int(round(h * scale / patch)) * patch), max(patch, int(round(w * scale / patch)) * patch))
    img = cv2.resize(image, (nw, nh), interpolation=cv2.INTER_AREA)
    m = cv2.resize(mask.astype(np.uint8), (nw, nh), interpolation=cv2.INTER_NEAREST).astype(bool)
    if not m.any():  # a thin region can vanish when shrinking: keep its nearest pixel
        ys, xs = np.nonzero(mask)
        m[min(nh - 1, int(ys.mean() * nh / h)), min(nw - 1, int(xs.mean() * nw / w))] = True
    return img, m
