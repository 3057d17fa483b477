"""Bilinear resizing of (C, H, W) float maps as two matrix products, with torch's ``interpolate`` semantics.

``F.interpolate(x, size, mode="bilinear", align_corners=False, antialias=...)`` is separable: each output row is
a fixed weighted sum of input rows, and likewise for columns. So a resize is ``Rh @ x @ Rwᵀ`` with the (out, in)
weight matrices built here, for any channel count (OpenCV's resize stops at 512 channels, a ViT-B map has 768)
and without torch. The weights follow ATen's CPU kernels (``UpSample.h`` area_pixel_compute_source_index for
plain bilinear; ``UpSampleKernel.cpp`` ``_compute_indices_weights_aa`` for the antialiased triangle filter), so
the features are torch's to float round-off (tests/test_features_resample.py).
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np


@lru_cache(maxsize=64)
def resize_weights(n_in: int, n_out: int, antialias: bool = False) -> np.ndarray:
    """(n_out, n_in) float32 weights of a bilinear resize along one axis (half-pixel centres); ``antialias``
    widens the triangle filter by the downscale factor, as torch's ``antialias=True`` does (no effect when
    enlarging)."""
    if n_in < 1 or n_out < 1:
        raise ValueError(f"sizes must be positive, got {n_in} -> {n_out}")
    scale = n_in / n_out
    out = np.arange(n_out, dtype=np.float64)
    weights = np.zeros((n_out, n_in), np.float64)
    if antialias and scale > 1.0:
        centre = scale * (out + 0.5)
        support = scale  # the bilinear filter's half-width 1, stretched by the scale
        first = np.maximum(np.trunc(centre - support + 0.5), 0).astype(int)
        last = np.minimum(np.trunc(centre + support + 0.5), n_in).astype(int)
        for i in range(n_out):
            taps = np.arange(first[i], last[i])
            w = np.clip(1.0 - np.abs((taps - centre[i] + 0.5) / scale), 0.0, None)
            weights[i, taps] = w / w.sum() if w.sum() > 0 else 0.0
        return weights.astype(np.float32)
    src = np.maximum(scale * (out + 0.5) - 0.5, 0.0)
    lo = np.minimum(np.floor(src).astype(int), n_in - 1)
    hi = np.minimum(lo + 1, n_in - 1)
    frac = src - lo
    rows = np.arange(n_out)
    np.add.at(weights, (rows, lo), 1.0 - frac)
    np.add.at(weights, (rows, hi), frac)
    return weights.astype(np.float32)


def resize_bilinear(x: np.ndarray, size: tuple[int, int], antialias: bool = False) -> np.ndarray:
    """(..., H, W) float array → (..., h, w) float32, ``size`` = (h, w)."""
    h, w = size
    x = np.asarray(x, np.float32)
    if x.shape[-2:] == (h, w):
        return x
    rows = resize_weights(x.shape[-2], h, antialias)
    cols = resize_weights(x.shape[-1], w, antialias)
    return np.matmul(np.matmul(rows, x), cols.T)


def l2_normalise(x: np.ndarray, axis: int, eps: float = 1e-12) -> np.ndarray:
    """``x`` divided by its L2 norm along ``axis`` (at least ``eps``), as torch's ``F.normalize``."""
    norm = np.sqrt(np.sum(np.square(x, dtype=np.float32), axis=axis, keepdims=True))
    return x / np.maximum(norm, np.float32(eps))
