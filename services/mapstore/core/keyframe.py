"""Keyframe records and their anchored points.

A keyframe's points live in its own camera frame (from its latest disparity on the 1/8 grid); world
coordinates come from its latest `world_from_cam`, so a pose update moves exactly its points.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import NamedTuple

import numpy as np

from services.mapstore.config import PointParams
from services.mapstore.core.geometry import backproject_grid, grid_intrinsics, transform_points


@dataclass(frozen=True)
class KeyframeContent:
    """What the features service sends for a keyframe (appearance; no geometry).

    Fields:
        kf_id: keyframe id (its frame `seq`), int.
        t_ns: timestamp, int64 nanoseconds.
        codes: (h, w, K) float16 PCA codes on the 1/8 grid; None while they have not arrived (features sends a
            keyframe's geometry at once and its codes later): the keyframe is fused for geometry only.
        colours: (h, w, 3) uint8 RGB sampled at the grid cell centres.
        image_hw: (H, W) working resolution in pixels (H = 8h, W = 8w).
        pca_version: version of the PCA basis the codes belong to (-1 without codes).
    """

    kf_id: int
    t_ns: int
    codes: np.ndarray | None
    colours: np.ndarray
    image_hw: tuple[int, int]
    pca_version: int

    def __post_init__(self) -> None:
        if self.colours.ndim != 3 or self.colours.shape[2] != 3:
            raise ValueError(f"colours must be (h, w, 3), got {self.colours.shape}")
        h, w = self.colours.shape[:2]
        if self.codes is not None and (self.codes.ndim != 3 or self.codes.shape[:2] != (h, w)):
            raise ValueError(f"codes must be ({h}, {w}, K) like the colours, got {self.codes.shape}")
        if tuple(self.image_hw) != (8 * h, 8 * w):
            raise ValueError(f"image_hw {self.image_hw} does not match a {h}x{w} grid")

    @property
    def has_codes(self) -> bool:
        """Whether the keyframe's codes are in (else it contributes geometry and colours only)."""
        return self.codes is not None

    @property
    def grid_shape(self) -> tuple[int, int]:
        """(h, w) of the 1/8 grid."""
        return self.colours.shape[:2]


@dataclass(frozen=True)
class KeyframeDepth:
    """Per-cell geometry from bundle adjustment (all maps (h, w) float32 on the 1/8 grid).

    Fields:
        disparity: inverse depth (1/m in a metric map, else arbitrary consistent units); 0 = unknown.
        intrinsics: (4,) float64 (fx, fy, cx, cy) in working-resolution pixels.
        static_weight: ARK static weight in [0, 1] (1 = static); None = all static.
        confidence: flow confidence in [0, 1]; None = all 1.
    """

    disparity: np.ndarray
    intrinsics: np.ndarray
    static_weight: np.ndarray | None = None
    confidence: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.disparity.ndim != 2:
            raise ValueError(f"disparity must be (h, w), got {self.disparity.shape}")
        for name in ("static_weight", "confidence"):
            arr = getattr(self, name)
            if arr is not None and arr.shape != self.disparity.shape:
                raise ValueError(f"{name} shape {arr.shape} != disparity {self.disparity.shape}")
        if np.asarray(self.intrinsics).shape != (4,):
            raise ValueError("intrinsics must be (4,) = (fx, fy, cx, cy)")

    def same_as(self, other: "KeyframeDepth | None") -> bool:
        """Every field equal to ``other``'s, value for value (a map resent unchanged)."""
        def equal(a: np.ndarray | None, b: np.ndarray | None) -> bool:
            return a is b if a is None or b is None else np.array_equal(a, b)

        return other is not None and all(equal(getattr(self, f.name), getattr(other, f.name)) for f in fields(self))


class AnchoredPoints(NamedTuple):
    """The usable cells of one keyframe (M of its h·w cells)."""

    cells: np.ndarray  # (M,) int64 flat cell index r·w + c
    points_cam: np.ndarray  # (M, 3) float64 in the keyframe's camera frame
    base_weight: np.ndarray  # (M,) float64 confidence × static weight (before consistency)


def candidate_points(depth: KeyframeDepth, params: PointParams) -> AnchoredPoints:
    """Cells with known depth that are not marked dynamic, in the keyframe's camera frame.

    Args:
        depth: the keyframe's latest geometry.
        params: thresholds for unknown depth and dynamic cells.
    Returns:
        AnchoredPoints with confidence × static weight per cell (consistency applied later).
    """
    disp = depth.disparity.astype(np.float64)
    static = np.ones_like(disp) if depth.static_weight is None else depth.static_weight.astype(np.float64)
    conf = np.ones_like(disp) if depth.confidence is None else depth.confidence.astype(np.float64)
    keep = (disp > params.min_disparity) & (static >= params.dynamic_threshold)
    keep &= np.isfinite(disp)
    if keep.any():
        median_disparity = float(np.median(disp[keep]))
        keep &= disp >= median_disparity / params.max_depth_ratio
    cells = np.flatnonzero(keep)
    pts = backproject_grid(depth.disparity, grid_intrinsics(depth.intrinsics)).reshape(-1, 3)[cells]
    return AnchoredPoints(cells, pts, (conf * static).reshape(-1)[cells])


def world_points(points_cam: np.ndarray, world_from_cam: np.ndarray) -> np.ndarray:
    """(M, 3) camera-frame points → (M, 3) float64 world points under `world_from_cam` (4, 4)."""
    return transform_points(np.asarray(world_from_cam, dtype=np.float64), points_cam)
