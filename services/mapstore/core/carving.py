"""Free-space carving: leave out points that later keyframes see through (objects that moved away).

A point p of keyframe i at depth z in a later view j is
- *seen through* (free space) when the nearest surface of j in a small neighbourhood of p's projection lies
  beyond (1 + free_margin)·z and j's cell there is reliable: j looked past the place p occupied, so whatever
  was there has gone (or p's depth was wrong — either way it does not belong in the map);
- *agreed with* when j's depth at the projection is within agree_tolerance of z;
- otherwise (occluded by something in front, or ambiguous) j says nothing about p.

Only views later than p's keyframe vote, and per point only the most recent deciding ones: an object that
arrived at a new place contradicts the earlier views of that (then empty) place, and stays, while the
place it left is seen empty by the views after the move. Margins are relative to depth, so a map with no
metric scale is carved the same as a metric one.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from services.mapstore.config import CarvingParams
from services.mapstore.core.geometry import grid_intrinsics, project, transform_points


class CarveView(NamedTuple):
    """One later keyframe as a carving witness (maps (h, w) on its 1/8 grid)."""

    cam_from_world: np.ndarray  # (4, 4) float64
    disparity: np.ndarray  # (h, w) float, 0 = unknown
    intrinsics: np.ndarray  # (4,) float64 working-resolution (fx, fy, cx, cy)
    reliability: np.ndarray | None  # (h, w) float in [0, 1]: flow confidence × static weight; None = all 1


class CarveVotes(NamedTuple):
    """The verdict of the most recent deciding views on each of M points."""

    deciding: np.ndarray  # (M,) int64 views that agreed with or saw through the point (≤ recent_views)
    seen_through: np.ndarray  # (M,) int64 of those, the views that saw through it
    carved: np.ndarray  # (M,) bool: the point is free space now and leaves the map


_FOOTPRINTS = {  # (base: how the projection picks the first cell, offsets of the cells around it)
    "cell": ("round", ((0, 0),)),
    "corners": ("floor", ((0, 0), (0, 1), (1, 0), (1, 1))),
    "3x3": ("round", tuple((dr, dc) for dr in (-1, 0, 1) for dc in (-1, 0, 1))),
}


def nearest_disparity_at(disparity: np.ndarray, u: np.ndarray, v: np.ndarray, footprint: str) -> np.ndarray:
    """Largest known disparity (the nearest surface) among the cells around each projection.

    Args:
        disparity: (h, w) float, 0 = unknown (unknown or outside cells never count as the nearest surface).
        u, v: (N,) float64 grid coordinates (cell centres at integers).
        footprint: "cell" (the cell the projection rounds to), "corners" (the 2×2 cells whose centres surround
            it) or "3x3" (the rounded cell and its 8 neighbours).
    Returns:
        (N,) float64; 0 where no cell of the footprint has a known depth.
    """
    if disparity.ndim != 2:
        raise ValueError(f"disparity must be (h, w), got {disparity.shape}")
    if footprint not in _FOOTPRINTS:
        raise ValueError(f"footprint must be one of {sorted(_FOOTPRINTS)}, got {footprint!r}")
    base, offsets = _FOOTPRINTS[footprint]
    pick = np.rint if base == "round" else np.floor
    r0, c0 = pick(v).astype(np.int64), pick(u).astype(np.int64)
    h, w = disparity.shape
    out = np.zeros(u.shape, np.float64)
    for dr, dc in offsets:
        r, c = r0 + dr, c0 + dc
        ok = (r >= 0) & (r < h) & (c >= 0) & (c < w)
        d = np.zeros(u.shape, np.float64)
        d[ok] = disparity[r[ok], c[ok]]
        np.maximum(out, np.where(np.isfinite(d), d, 0.0), out=out)
    return out


def free_space_votes(points_world: np.ndarray, views_newest_first: list[CarveView],
                     params: CarvingParams) -> CarveVotes:
    """Which points the most recent later views see through.

    Args:
        points_world: (M, 3) float64 world points of one keyframe.
        views_newest_first: later keyframes, most recent first (a point stops listening once
            `params.recent_views` views have decided on it).
        params: margins, how many views decide and how many must see through.
    Returns:
        CarveVotes per point.
    """
    if points_world.ndim != 2 or points_world.shape[1] != 3:
        raise ValueError(f"points must be (M, 3), got {points_world.shape}")
    m = points_world.shape[0]
    deciding = np.zeros(m, np.int64)
    through = np.zeros(m, np.int64)
    for view in views_newest_first:
        open_idx = np.flatnonzero(deciding < params.recent_views)
        if open_idx.size == 0:
            break
        agree, free, idx = _judge(points_world[open_idx], view, params)
        deciding[open_idx[idx[agree | free]]] += 1
        through[open_idx[idx[free]]] += 1
    carved = (through >= params.min_violations) & (2 * through > deciding)
    return CarveVotes(deciding, through, carved)


def _judge(points_world: np.ndarray, view: CarveView, params: CarvingParams):
    """(agree, free, idx): per point landing on a known cell of `view` (indices idx into the input)."""
    h, w = view.disparity.shape
    proj = project(transform_points(view.cam_from_world, points_world), grid_intrinsics(view.intrinsics))
    col, row = np.rint(proj.u), np.rint(proj.v)
    inside = (proj.z > 0) & (col >= 0) & (col < w) & (row >= 0) & (row < h)
    idx = np.flatnonzero(inside)
    r, c = row[idx].astype(np.int64), col[idx].astype(np.int64)
    disp = view.disparity[r, c].astype(np.float64)
    known = np.isfinite(disp) & (disp > 0)
    idx, r, c, disp = idx[known], r[known], c[known], disp[known]
    z = proj.z[idx]
    z_view = 1.0 / disp
    agree = np.abs(z - z_view) <= params.agree_tolerance * z_view
    near = nearest_disparity_at(view.disparity, proj.u[idx], proj.v[idx], params.footprint)
    reliable = np.ones(idx.size, bool) if view.reliability is None else view.reliability[r, c] >= params.min_reliability
    free = (1.0 / near > (1.0 + params.free_margin) * z) & reliable & ~agree
    return agree, free, idx
