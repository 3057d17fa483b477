"""Multi-scale dense DINO features on the 1/8 grid.

For each scale σ the working image is resized to (σ·H, σ·W) rounded to multiples of the patch size, run
through the backbone, each patch-feature map is L2-normalised per pixel, bilinearly upsampled to the 1/8
grid (H/8, W/8) and blended with weights w_σ = σ / Σσ (finer scales see smaller detail, so they weigh more;
KM-ViPE's choice). The blend is L2-normalised again: downstream only cosine similarities matter.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable, NamedTuple

import numpy as np

from .geometry import GRID_STRIDE
from .resample import l2_normalise, resize_bilinear

Backbone = Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True)
class PyramidParams:
    scales: tuple[float, ...] = (2.0, 1.5, 1.0, 0.75)
    """Resize factors of the working image fed to the backbone (paper: {2.0, 1.5, 1.0, 0.75})."""
    patch_size: int = 14
    """ViT patch size; each scaled side is rounded to a multiple of it."""

    def __post_init__(self) -> None:
        if not self.scales or any(s <= 0 for s in self.scales):
            raise ValueError(f"scales must be a non-empty tuple of positive factors, got {self.scales}")


class PyramidFeatures(NamedTuple):
    features: np.ndarray
    """(C, H/8, W/8) float32, unit L2 norm per grid cell."""
    seconds_per_scale: dict[float, float]
    """Wall time of each scale (resize + backbone + upsample), for benchmarks."""


def scale_weights(scales: tuple[float, ...]) -> list[float]:
    """w_σ = σ / Σσ."""
    total = float(sum(scales))
    return [s / total for s in scales]


def scaled_size(height: int, width: int, scale: float, patch: int) -> tuple[int, int]:
    """(σ·H, σ·W) rounded to the nearest multiple of ``patch`` (at least one patch)."""
    return max(patch, int(round(height * scale / patch)) * patch), max(patch, int(round(width * scale / patch)) * patch)


def backbone_map(image: np.ndarray, backbone: Backbone, scale: float, patch: int) -> np.ndarray:
    """(1, 3, H, W) normalised image → (1, C, h_σ, w_σ) unit-norm patch features at scale σ."""
    h, w = scaled_size(image.shape[2], image.shape[3], scale, patch)
    x = resize_bilinear(image, (h, w), antialias=scale < 1.0)
    return l2_normalise(np.asarray(backbone(x), np.float32), axis=1)


def multiscale_features(image: np.ndarray, backbone: Backbone, params: PyramidParams = PyramidParams()) -> PyramidFeatures:
    """Blend of the backbone's features over ``params.scales`` on the 1/8 grid.

    ``image``: (1, 3, H, W) float32 ImageNet-normalised RGB, H and W multiples of 8 (the working image).
    """
    if image.ndim != 4 or image.shape[:2] != (1, 3):
        raise ValueError(f"image must be (1, 3, H, W), got {tuple(image.shape)}")
    H, W = image.shape[2:]
    if H % GRID_STRIDE or W % GRID_STRIDE:
        raise ValueError(f"working image sides must be multiples of {GRID_STRIDE}, got {H}×{W}")
    grid = (H // GRID_STRIDE, W // GRID_STRIDE)
    blend, seconds = None, {}
    for scale, weight in zip(params.scales, scale_weights(params.scales)):
        t0 = time.perf_counter()
        fmap = backbone_map(image, backbone, scale, params.patch_size)
        up = resize_bilinear(fmap[0], grid)
        blend = np.float32(weight) * up if blend is None else blend + np.float32(weight) * up
        seconds[scale] = time.perf_counter() - t0
    return PyramidFeatures(l2_normalise(blend, axis=0), seconds)
