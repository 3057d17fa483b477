"""Keyframe selection by dense optical flow (OpenCV DIS) against the last keyframe.

A frame becomes a keyframe when the mean flow magnitude on the 1/8 grid, in grid pixels, exceeds a
threshold (≈ 2.4 grid px as ViPE). The first frame is always a keyframe; the service promotes the last frame
on end of stream. Flow is computed on a downscaled grey image (``flow_scale`` of the working size), which
is enough to measure motion of a few grid pixels and keeps non-keyframes cheap.

Robust mean: the largest ``outlier_fraction`` of cell magnitudes are dropped before averaging, so an object
moving in front of a static camera (a small fraction of the cells, with large or garbage flow) does not
trigger keyframes; camera motion moves most cells and still does.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np

from services.common.image_texture import texture

from .geometry import GRID_STRIDE

_PRESETS = {
    "ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
    "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
    "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
}


@dataclass(frozen=True)
class KeyframeParams:
    threshold_grid_px: float = 2.4
    """New keyframe when the robust mean flow magnitude (1/8-grid pixels) exceeds this."""
    flow_scale: float = 0.5
    """Flow runs on the grey working image resized by this factor (0.5: 1/2 working resolution)."""
    dis_preset: str = "ultrafast"
    """OpenCV DIS preset: ultrafast, fast or medium."""
    outlier_fraction: float = 0.2
    """Fraction of the largest cell magnitudes dropped before averaging (0: plain mean)."""
    min_texture: float = 0.5
    """A frame whose mean absolute grey difference between neighbouring pixels (at flow scale) is below this shows
    nothing (a black frame, a lens cap in the dark): never a keyframe, and the first frame that shows something
    again is one. The synthetic bare wall (low_texture profile) goes down to 1.1 and is still tracked; real
    sequences here 3.9 (TartanAir's walls) to 19. A covered lens whose sensor noise exceeds this is not caught
    here; ba's photometric check still reports its frames as a lost view."""

    def __post_init__(self) -> None:
        if self.dis_preset not in _PRESETS:
            raise ValueError(f"dis_preset must be one of {sorted(_PRESETS)}, got {self.dis_preset!r}")
        if not 0.0 < self.flow_scale <= 1.0:
            raise ValueError(f"flow_scale must be in (0, 1], got {self.flow_scale}")
        if not 0.0 <= self.outlier_fraction < 1.0:
            raise ValueError(f"outlier_fraction must be in [0, 1), got {self.outlier_fraction}")


class KeyframeDecision(NamedTuple):
    is_keyframe: bool
    motion_grid_px: float
    """Robust mean flow magnitude against the last keyframe in 1/8-grid pixels (inf for the first frame)."""


def grid_flow_magnitude(flow: np.ndarray, grid_hw: tuple[int, int], flow_scale: float) -> np.ndarray:
    """(h, w, 2) flow in flow-image pixels → (H/8, W/8) magnitude in 1/8-grid pixels (cell-averaged flow)."""
    cells = cv2.resize(flow, (grid_hw[1], grid_hw[0]), interpolation=cv2.INTER_AREA)
    return np.linalg.norm(cells, axis=2) / (flow_scale * GRID_STRIDE)


def robust_mean(values: np.ndarray, outlier_fraction: float) -> float:
    """Mean of ``values`` without its largest ``outlier_fraction``."""
    flat = np.sort(values.ravel())
    keep = max(1, int(round(flat.size * (1.0 - outlier_fraction))))
    return float(flat[:keep].mean())


class KeyframeSelector:
    """Stateful selector: feed every frame's grey working image in order to :meth:`observe`."""

    def __init__(self, params: KeyframeParams = KeyframeParams()):
        self.params = params
        self._dis = cv2.DISOpticalFlow_create(_PRESETS[params.dis_preset])
        self._ref: np.ndarray | None = None
        self._flow: np.ndarray | None = None  # the previous frame's flow from the reference, DIS's start
        self._grid_hw: tuple[int, int] | None = None
        self._blind = False  # frames since the reference showed nothing (min_texture)

    def _small(self, grey: np.ndarray) -> np.ndarray:
        if grey.ndim != 2 or grey.dtype != np.uint8:
            raise ValueError(f"expected (H, W) uint8 grey working image, got {grey.shape} {grey.dtype}")
        if grey.shape[0] % GRID_STRIDE or grey.shape[1] % GRID_STRIDE:
            raise ValueError(f"working image sides must be multiples of {GRID_STRIDE}, got {grey.shape}")
        s = self.params.flow_scale
        if s == 1.0:
            return np.ascontiguousarray(grey)
        size = (max(8, int(round(grey.shape[1] * s))), max(8, int(round(grey.shape[0] * s))))
        return cv2.resize(grey, size, interpolation=cv2.INTER_AREA)

    def motion(self, grey: np.ndarray) -> float:
        """Robust mean grid-pixel motion of ``grey`` against the last keyframe (inf when there is none)."""
        small = self._small(grey)
        if self._ref is None:
            return float("inf")
        if small.shape != self._ref.shape:
            raise ValueError(f"frame size changed from {self._ref.shape} to {small.shape} (flow scale)")
        # DIS refines a flow passed to calc() (same size, float32 2-channel). Started from the previous frame's
        # flow it follows motions far beyond its own search range: from zero, a reference 40 frames behind a car
        # (KITTI 07) gave near-zero flow and no keyframes at all.
        self._flow = flow = self._dis.calc(self._ref, small, self._flow)  # refined in place
        grid_hw = (grey.shape[0] // GRID_STRIDE, grey.shape[1] // GRID_STRIDE)
        # flow pixels → working pixels uses the actual small/working ratio, not the nominal flow_scale
        scale = small.shape[1] / grey.shape[1]
        return robust_mean(grid_flow_magnitude(flow, grid_hw, scale), self.params.outlier_fraction)

    def observe(self, grey: np.ndarray) -> KeyframeDecision:
        """Decide for the next frame; a keyframe becomes the new flow reference. A frame that shows nothing is
        not a keyframe (motion 0); the first that shows something after such frames is: DIS over blank frames
        returns a smooth flow that says nothing, and chained from it the motion since the reference is lost
        (the synthetic orbit after 20 blank frames: the next keyframe 8 frames later, tracked 0.2-0.9 m off)."""
        if self._ref is not None and texture(self._small(grey)) < self.params.min_texture:
            self._blind = True
            return KeyframeDecision(False, 0.0)
        m = self.motion(grey)
        is_kf = m > self.params.threshold_grid_px or self._blind
        if is_kf:
            self.set_reference(grey)
        return KeyframeDecision(bool(is_kf), m)

    def set_reference(self, grey: np.ndarray) -> None:
        """Make ``grey`` the last keyframe (used on EOS promotion and after :meth:`observe`)."""
        self._ref = self._small(grey).copy()
        self._flow = None
        self._blind = False
