"""Multi-view depth consistency: does a keyframe's depth agree with its neighbours' depths?

A point of keyframe i projected into neighbour j is *checked* when it lands on a cell of j with known
depth and is not occluded there (z_proj ≤ (1 + tol) z_j); it *agrees* when |z_proj − z_j| ≤ tol · z_j.
A point in front of what j sees (z_proj < (1 − tol) z_j) is a free-space violation: j looked through
it, so it moved or its depth is wrong. Consistency = agreeing / checked views.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from services.mapstore.config import ConsistencyParams
from services.mapstore.core.geometry import grid_intrinsics, project, transform_points


class NeighbourView(NamedTuple):
    """One neighbour keyframe as seen by the consistency check."""

    cam_from_world: np.ndarray  # (4, 4) float64
    disparity: np.ndarray  # (h, w) float, 0 = unknown
    intrinsics: np.ndarray  # (4,) float64 working-resolution (fx, fy, cx, cy)


def depth_consistency(
    points_world: np.ndarray, neighbours: list[NeighbourView], params: ConsistencyParams
) -> np.ndarray:
    """Fraction of the neighbours that can check a point and agree with its depth.

    Args:
        points_world: (M, 3) float64 world points of one keyframe.
        neighbours: views of the neighbouring keyframes (latest poses and depths).
        params: relative depth tolerance and the value for unchecked points.
    Returns:
        (M,) float64 in [0, 1]; `params.unverified` where no neighbour checks the point.
    """
    m = points_world.shape[0]
    checked = np.zeros(m)
    agreed = np.zeros(m)
    for nb in neighbours:
        h, w = nb.disparity.shape
        proj = project(transform_points(nb.cam_from_world, points_world), grid_intrinsics(nb.intrinsics))
        col = np.rint(proj.u)
        row = np.rint(proj.v)
        inside = (proj.z > 0) & (col >= 0) & (col < w) & (row >= 0) & (row < h)
        idx = np.flatnonzero(inside)
        disp = nb.disparity[row[idx].astype(np.int64), col[idx].astype(np.int64)].astype(np.float64)
        known = disp > 0
        idx, disp = idx[known], disp[known]
        z_nb = 1.0 / disp
        z = proj.z[idx]
        tol = params.rel_tolerance * z_nb
        not_occluded = z <= z_nb + tol
        checked[idx[not_occluded]] += 1.0
        agreed[idx[np.abs(z - z_nb) <= tol]] += 1.0
    out = np.full(m, params.unverified)
    has = checked > 0
    out[has] = agreed[has] / checked[has]
    return out
