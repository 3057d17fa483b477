"""Working resolution and intrinsics bookkeeping (docs/CONVENTIONS.md: pixel centres at integers).

Resizing by (sx, sy): ``fx' = sx·fx``, ``cx' = sx·(cx + 0.5) − 0.5`` (same for y). The 1/8 grid is the
same rule with s = 1/8.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np

from services.common.camera import scale_intrinsics

GRID_STRIDE = 8


@dataclass(frozen=True)
class ResolutionParams:
    target_area: int = 384 * 512
    """Pixels of the working image (≈ 384×512 as ViPE); aspect ratio of the input is kept."""
    multiple: int = 8
    """Both working sides are multiples of this (the 1/8 grid needs 8)."""
    fov_deg: float = 60.0
    """Field-of-view prior (degrees, across the longer image side) when no intrinsics are given."""


class Intrinsics(NamedTuple):
    """Pinhole intrinsics in pixels of the image they belong to (float64 semantics)."""

    fx: float
    fy: float
    cx: float
    cy: float

    def scaled(self, sx: float, sy: float) -> "Intrinsics":
        """Intrinsics of this image resized by (sx, sy) (new = old · s)."""
        return Intrinsics(*(float(v) for v in scale_intrinsics(self.as_array(), sx, sy)))

    def to_grid(self) -> "Intrinsics":
        """Intrinsics of the 1/8 grid of this (working) image."""
        return self.scaled(1.0 / GRID_STRIDE, 1.0 / GRID_STRIDE)

    def as_array(self) -> np.ndarray:
        """(4,) float64 ``[fx, fy, cx, cy]``."""
        return np.array(self, dtype=np.float64)


class WorkingSize(NamedTuple):
    """Working image size and the per-axis scale from the original (working = original · scale)."""

    height: int
    width: int
    scale_y: float
    scale_x: float


def working_size(height: int, width: int, params: ResolutionParams = ResolutionParams()) -> WorkingSize:
    """Working size for an ``height``×``width`` input: area ≈ ``target_area``, sides multiples of ``multiple``.

    The two sides are rounded independently, so the scales differ by < multiple/side (≤ 3 % at 240 px).
    """
    if height <= 0 or width <= 0:
        raise ValueError(f"image size must be positive, got {height}×{width}")
    s = math.sqrt(params.target_area / (height * width))
    m = params.multiple
    h = max(m, int(round(height * s / m)) * m)
    w = max(m, int(round(width * s / m)) * m)
    return WorkingSize(h, w, h / height, w / width)


def resize_to_working(image: np.ndarray, size: WorkingSize) -> np.ndarray:
    """(H, W[, C]) uint8 image → working size (area interpolation when shrinking, linear when growing)."""
    shrink = size.height < image.shape[0]
    interp = cv2.INTER_AREA if shrink else cv2.INTER_LINEAR
    return cv2.resize(image, (size.width, size.height), interpolation=interp)


def to_rgb(image: np.ndarray) -> np.ndarray:
    """(H, W) grey or (H, W, 3) RGB uint8 → (H, W, 3) RGB (grey replicated to three channels)."""
    if image.ndim == 2:
        return np.repeat(image[:, :, None], 3, axis=2)
    if image.ndim == 3 and image.shape[2] == 3:
        return image
    raise ValueError(f"expected (H, W) or (H, W, 3) image, got {image.shape}")


def to_grey(image: np.ndarray) -> np.ndarray:
    """(H, W, 3) RGB or (H, W) uint8 → (H, W) uint8 grey."""
    return image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)


def fov_prior(height: int, width: int, fov_deg: float = ResolutionParams.fov_deg) -> Intrinsics:
    """Intrinsics from a field of view across the longer side; principal point at the image centre.

    60° is a middle guess between phone main cameras (≈ 65–75°) and webcams/dashcams (≈ 55–90°); ba refines
    the focal length, so the guess only needs to be within its basin (≈ ±30 %).
    """
    if not 1.0 < fov_deg < 179.0:
        raise ValueError(f"fov_deg must be in (1, 179), got {fov_deg}")
    f = 0.5 * max(height, width) / math.tan(math.radians(fov_deg) / 2.0)
    return Intrinsics(f, f, (width - 1) / 2.0, (height - 1) / 2.0)
