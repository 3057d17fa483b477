"""The resize rule of docs/CONVENTIONS.md, in one place: intrinsics of an image resized by (sx, sy).

Every service resizes (features to the working size, ba to the 1/8 grid and to half size for frames, the mapstore
to the grid, the viewer to the source size), and the rule has one subtle term (pixel centres at integers, so the
principal point moves by half a pixel): written once here, not once per service.
"""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike


def scale_intrinsics(intrinsics: ArrayLike, sx: float, sy: float) -> np.ndarray:
    """(4,) float64 ``fx, fy, cx, cy`` of an image resized by ``sx`` across and ``sy`` down (new = old · s):
    ``fx' = sx·fx``, ``cx' = sx·(cx + 0.5) − 0.5``, and the same for y."""
    fx, fy, cx, cy = (float(v) for v in np.asarray(intrinsics, np.float64).reshape(4))
    return np.array([sx * fx, sy * fy, sx * (cx + 0.5) - 0.5, sy * (cy + 0.5) - 0.5])
