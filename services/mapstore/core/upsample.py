"""Denser keyframe points: the 1/8-grid disparity upsampled by an integer factor, optionally guided by the image.

Output grid at factor f: cells of s = 8/f working pixels; cell (r, c) has its centre at working pixel
(s·c + (s−1)/2, s·r + (s−1)/2), i.e. at ((s·c + (s−1)/2 − 3.5)/8, …) in 1/8-grid coordinates (CONVENTIONS.md).

- ``nearest``: each output cell takes the disparity of the 1/8 cell it lies in (no new information);
- ``bilinear``: bilinear in disparity between the four surrounding 1/8 cells (unknown cells left out);
- ``guided``: joint bilateral upsampling (Kopf et al. 2007): the 3×3 surrounding 1/8 cells weighted by a
  spatial Gaussian times a colour Gaussian between the output cell's mean colour and each 1/8 cell's, so
  depth edges follow colour edges instead of being smeared across them.

Disparity 0 means unknown in and out; an output cell is unknown when no known 1/8 cell carries weight.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np

GRID_STRIDE = 8
GUIDE_MIN_WEIGHT = 1e-6
"""Below this total colour-and-space weight the guided method falls back to spatial weights alone (no 1/8 cell
around resembles the output cell: texture, or noise)."""
Method = Literal["nearest", "bilinear", "guided"]


@dataclass(frozen=True)
class UpsampleParams:
    """How the 1/8-grid disparity is upsampled."""

    factor: int = 2
    """Output cells per 1/8 cell along each side (1, 2, 4 or 8: the output stride 8/factor must be whole)."""
    method: Method = "guided"
    """nearest, bilinear or guided (joint bilateral with the keyframe image)."""
    sigma_space: float = 0.6
    """Spatial Gaussian of the guided method, in 1/8-grid cells."""
    sigma_colour: float = 12.0
    """Colour Gaussian of the guided method, in 0..255 RGB units (Euclidean over the three channels)."""

    def __post_init__(self) -> None:
        if self.factor < 1 or GRID_STRIDE % self.factor:
            raise ValueError(f"factor must divide {GRID_STRIDE}, got {self.factor}")
        if self.method not in ("nearest", "bilinear", "guided"):
            raise ValueError(f"method must be nearest, bilinear or guided, got {self.method!r}")
        if self.sigma_space <= 0 or self.sigma_colour <= 0:
            raise ValueError("sigma_space and sigma_colour must be > 0")


def output_centres(h: int, w: int, factor: int) -> tuple[np.ndarray, np.ndarray]:
    """1/8-grid coordinates (rows (h·f,), cols (w·f,)) float64 of the output cell centres."""
    s = GRID_STRIDE / factor
    to_grid = lambda n: ((s * np.arange(n) + (s - 1) / 2) - (GRID_STRIDE - 1) / 2) / GRID_STRIDE  # noqa: E731
    return to_grid(h * factor), to_grid(w * factor)


def upsample_disparity(disparity: np.ndarray, image: np.ndarray | None, params: UpsampleParams) -> np.ndarray:
    """(h, w) float disparity (0 = unknown) → (h·f, w·f) float32.

    ``image``: (8h, 8w, 3) uint8 RGB working image; needed by the guided method only.
    """
    disp = np.asarray(disparity, np.float64)
    if disp.ndim != 2:
        raise ValueError(f"disparity must be (h, w), got {disp.shape}")
    h, w, f = *disp.shape, params.factor
    if params.method == "nearest" or f == 1:
        return np.repeat(np.repeat(disp, f, 0), f, 1).astype(np.float32)
    rows, cols = output_centres(h, w, f)
    if params.method == "bilinear":
        return _bilinear(disp, rows, cols).astype(np.float32)
    if image is None or image.shape != (GRID_STRIDE * h, GRID_STRIDE * w, 3):
        raise ValueError(f"guided upsampling needs the ({8 * h}, {8 * w}, 3) working image, got "
                         f"{None if image is None else image.shape}")
    return _guided(disp, image, rows, cols, params).astype(np.float32)


def _bilinear(disp: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    h, w = disp.shape
    r0 = np.clip(np.floor(rows).astype(int), 0, h - 1)
    c0 = np.clip(np.floor(cols).astype(int), 0, w - 1)
    r1, c1 = np.minimum(r0 + 1, h - 1), np.minimum(c0 + 1, w - 1)
    fr = np.clip(rows - r0, 0, 1)[:, None]
    fc = np.clip(cols - c0, 0, 1)[None, :]
    acc = np.zeros((len(rows), len(cols)))
    norm = np.zeros_like(acc)
    for rr, cc, wgt in ((r0, c0, (1 - fr) * (1 - fc)), (r0, c1, (1 - fr) * fc), (r1, c0, fr * (1 - fc)), (r1, c1, fr * fc)):
        d = disp[np.ix_(rr, cc)]
        known = (d > 0) * wgt
        acc += known * d
        norm += known
    return np.where(norm > 1e-9, acc / np.maximum(norm, 1e-12), 0.0)


def _guided(disp: np.ndarray, image: np.ndarray, rows: np.ndarray, cols: np.ndarray, params: UpsampleParams) -> np.ndarray:
    h, w = disp.shape
    H, W = len(rows), len(cols)
    img = image.astype(np.float32)
    fine = cv2.resize(img, (W, H), interpolation=cv2.INTER_AREA).astype(np.float64)  # mean colour per output cell
    coarse = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA).astype(np.float64)  # … per 1/8 cell
    r_near, c_near = np.rint(rows).astype(int), np.rint(cols).astype(int)
    acc, norm = np.zeros((H, W)), np.zeros((H, W))
    acc_space, norm_space = np.zeros((H, W)), np.zeros((H, W))  # fallback where no neighbour's colour is close
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            rr, cc = np.clip(r_near + dr, 0, h - 1), np.clip(c_near + dc, 0, w - 1)
            dist2 = (rows - rr)[:, None] ** 2 + (cols - cc)[None, :] ** 2
            colour2 = ((fine - coarse[np.ix_(rr, cc)]) ** 2).sum(-1)
            d = disp[np.ix_(rr, cc)]
            space = np.exp(-dist2 / (2 * params.sigma_space**2)) * (d > 0)
            wgt = space * np.exp(-colour2 / (2 * params.sigma_colour**2))
            acc, norm = acc + wgt * d, norm + wgt
            acc_space, norm_space = acc_space + space * d, norm_space + space
    guided = norm > GUIDE_MIN_WEIGHT
    out = np.where(guided, acc / np.where(guided, norm, 1.0), acc_space / np.maximum(norm_space, 1e-300))
    return np.where(norm_space > 0, out, 0.0)
