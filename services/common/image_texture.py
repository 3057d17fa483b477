"""How much an image shows: the measure both features (a covered lens is never a keyframe) and ba (bare walls get
denser flow patches) read from a grey image."""
from __future__ import annotations

import numpy as np


def texture(grey: np.ndarray) -> float:
    """Mean absolute grey difference between horizontally and vertically neighbouring pixels, summed, of a
    ``(H, W)`` uint8 image (grey levels per pixel: 0 for a blank frame; KITTI 07 at the working size 9-15, the
    hand-held desk 7.5-10, TartanAir hospital's panelled walls 2.5-6)."""
    image = np.asarray(grey).astype(np.int16)
    return float(np.abs(np.diff(image, axis=1)).mean() + np.abs(np.diff(image, axis=0)).mean())
