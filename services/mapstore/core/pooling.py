"""Query by keyframe region: the 1/8-grid cells a box covers, their codes pooled, lifted to feature space.

A region of a keyframe the map already holds is described by the codes the map was built from, so no backbone is
needed to turn it into a query vector: the mean of the codes of the cells inside the region, decoded by the PCA
basis they were coded with (decoding is affine, so this is also the mean of the decoded cell features) and
L2-normalised — a vector in the backbone's space, scored against the map exactly as a text query's.

Boxes are normalised to the image: x = (u + 0.5) / W for a pixel coordinate u (pixel centres at integers,
docs/CONVENTIONS.md), so 0 is the image's left edge and 1 its right edge, whatever the resolution the viewer
shows it at. Cell (r, c) of an (h, w) grid is centred at ((c + 0.5) / w, (r + 0.5) / h).
"""

from __future__ import annotations

import numpy as np

_EPS = 1e-12


def check_box(box: np.ndarray) -> np.ndarray:
    """Validate a normalised box.

    Args:
        box: (4,) [x0, y0, x1, y1], each in [0, 1], x0 <= x1 and y0 <= y1 (equal: a point, e.g. a click).
    Returns:
        (4,) float64 box. Raises ValueError naming what is wrong.
    """
    b = np.asarray(box, np.float64)
    if b.shape != (4,) or not np.all(np.isfinite(b)):
        raise ValueError(f"box must be 4 finite numbers [x0, y0, x1, y1], got {np.asarray(box).tolist()}")
    shown = np.round(b, 4).tolist()
    if b.min() < 0.0 or b.max() > 1.0:
        raise ValueError(f"box {shown} must lie in [0, 1] (normalised to the image's width and height)")
    if b[0] > b[2] or b[1] > b[3]:
        raise ValueError(f"box {shown} is inverted: need x0 <= x1 and y0 <= y1")
    return b


def box_cells(grid_hw: tuple[int, int], box: np.ndarray) -> np.ndarray:
    """The cells of an (h, w) grid a normalised box covers.

    Args:
        grid_hw: (h, w) cells.
        box: (4,) normalised [x0, y0, x1, y1] (see `check_box`).
    Returns:
        (h, w) bool: cells whose centre lies inside the box (edges included); when none does (a box smaller than a
        cell, or a point), the one cell under the box's centre.
    """
    h, w = grid_hw
    x0, y0, x1, y1 = check_box(box)
    cx, cy = (np.arange(w) + 0.5) / w, (np.arange(h) + 0.5) / h
    mask = ((cy >= y0) & (cy <= y1))[:, None] & ((cx >= x0) & (cx <= x1))[None, :]
    if not mask.any():
        r = min(int((y0 + y1) / 2 * h), h - 1)  # the centre's cell; a centre on the far edge is in the last cell
        c = min(int((x0 + x1) / 2 * w), w - 1)
        mask[r, c] = True
    return mask


def pool_codes(codes: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Mean code of the masked cells.

    Args:
        codes: (h, w, K) codes of a keyframe (any float dtype).
        mask: (h, w) bool, at least one cell set.
    Returns:
        (K,) float64 mean code.
    """
    if codes.ndim != 3 or mask.shape != codes.shape[:2]:
        raise ValueError(f"codes (h, w, K) and mask (h, w) must share their grid; got {codes.shape}, {mask.shape}")
    if not mask.any():
        raise ValueError("the region covers no cell")
    return codes[mask].astype(np.float64).mean(axis=0)


def lift_code(code: np.ndarray, mean: np.ndarray, components: np.ndarray) -> np.ndarray:
    """Decode a code to backbone space and L2-normalise it.

    Args:
        code: (K,) code in the basis (mean, components).
        mean: (D,) basis mean μ.
        components: (K, D) basis rows V.
    Returns:
        (D,) float32 unit vector (μ + Vᵀz)/‖μ + Vᵀz‖ (zero when the decoded feature is zero).
    """
    if components.ndim != 2 or code.shape != (components.shape[0],) or mean.shape != (components.shape[1],):
        raise ValueError(f"code (K,), mean (D,), components (K, D) disagree: {code.shape}, {mean.shape}, "
                         f"{components.shape}")
    f = mean.astype(np.float64) + code.astype(np.float64) @ components.astype(np.float64)
    return (f / max(float(np.linalg.norm(f)), _EPS)).astype(np.float32)


def region_vector(codes: np.ndarray, box: np.ndarray, mean: np.ndarray, components: np.ndarray) -> np.ndarray:
    """A keyframe region's query vector: `box_cells` → `pool_codes` → `lift_code`.

    Args:
        codes: (h, w, K) the keyframe's codes; box: (4,) normalised; mean (D,), components (K, D): their basis.
    Returns:
        (D,) float32 unit vector in backbone space.
    """
    return lift_code(pool_codes(codes, box_cells(codes.shape[:2], box)), mean, components)
