"""Shape the mapstore's flat answers into ranked regions per query, and summarise segmentations.

Everything here takes and returns numpy arrays; world coordinates are the map's (metres when the map is
metric, else the map's consistent arbitrary unit).
"""
from __future__ import annotations

import colorsys
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class RegionParams:
    """How regions are presented."""

    samples_per_region: int = 8
    """Top-scoring points of the query kept per region as its sample points."""
    box_margin: float = 1e-4
    """Relative slack on a region's box when deciding which top points fall inside it."""


@dataclass(frozen=True)
class Region:
    """One connected high-scoring part of the map for one query."""

    score: float  # the region's score (mapstore's definition: mean cosine of its voxels)
    centroid: np.ndarray  # (3,) float32, world frame
    box_min: np.ndarray  # (3,) float32, world frame, axis-aligned
    box_max: np.ndarray  # (3,) float32
    count: int  # map points (voxels) in the region
    samples: np.ndarray  # (S, 3) float32 sample points, best first
    sample_scores: np.ndarray  # (S,) float32


@dataclass(frozen=True)
class QueryResult:
    """Regions (best first) and top points of one query vector."""

    regions: list[Region]
    top_xyz: np.ndarray  # (P, 3) float32, best first
    top_scores: np.ndarray  # (P,) float32


def _check(name: str, a: np.ndarray, shape: tuple) -> np.ndarray:
    a = np.asarray(a)
    if a.ndim != len(shape) or any(w is not None and n != w for n, w in zip(a.shape, shape)):
        raise ValueError(f"{name} must have shape {shape}, got {a.shape}")
    return a


def group_answer(
    n_queries: int,
    region_query: np.ndarray, region_score: np.ndarray, region_centroid: np.ndarray,
    region_box_min: np.ndarray, region_box_max: np.ndarray, region_count: np.ndarray,
    point_query: np.ndarray, point_xyz: np.ndarray, point_score: np.ndarray,
    params: RegionParams = RegionParams(),
) -> list[QueryResult]:
    """Flat arrays (R regions, P points, each tagged with its query index) → one :class:`QueryResult` per query.

    Regions are sorted by score, best first; each gets as samples the query's top points inside its box.
    """
    r = len(_check("region_query", region_query, (None,)))
    for name, a, shape in (("region_score", region_score, (r,)), ("region_centroid", region_centroid, (r, 3)),
                           ("region_box_min", region_box_min, (r, 3)), ("region_box_max", region_box_max, (r, 3)),
                           ("region_count", region_count, (r,))):
        _check(name, a, shape)
    p = len(_check("point_query", point_query, (None,)))
    _check("point_xyz", point_xyz, (p, 3))
    _check("point_score", point_score, (p,))
    results = []
    for q in range(n_queries):
        pts = np.flatnonzero(point_query == q)
        pts = pts[np.argsort(-point_score[pts], kind="stable")]
        xyz, scores = point_xyz[pts].astype(np.float32), point_score[pts].astype(np.float32)
        regs = np.flatnonzero(region_query == q)
        regs = regs[np.argsort(-region_score[regs], kind="stable")]
        regions = [_region(i, region_score, region_centroid, region_box_min, region_box_max, region_count,
                           xyz, scores, params) for i in regs]
        results.append(QueryResult(regions, xyz, scores))
    return results


def _region(i, score, centroid, bmin, bmax, count, xyz, scores, params: RegionParams) -> Region:
    lo, hi = np.asarray(bmin[i], np.float32), np.asarray(bmax[i], np.float32)
    slack = params.box_margin * max(float(np.max(hi - lo)), 1.0)
    inside = np.all((xyz >= lo - slack) & (xyz <= hi + slack), axis=1) if len(xyz) else np.zeros(0, bool)
    keep = np.flatnonzero(inside)[: params.samples_per_region]
    return Region(float(score[i]), np.asarray(centroid[i], np.float32), lo, hi, int(count[i]),
                  xyz[keep], scores[keep])


@dataclass(frozen=True)
class LabelSummary:
    """Points given one label by a segmentation."""

    count: int
    mean_score: float  # mean cosine score of those points (nan when count is 0)
    centroid: np.ndarray  # (3,) float32 (nan when count is 0)


def segment_summary(label: np.ndarray, score: np.ndarray, xyz: np.ndarray, n_labels: int) -> list[LabelSummary]:
    """Per label index in [0, n_labels): count, mean score and centroid of its points.

    label: (N,) int, −1 = unlabelled; score: (N,) float; xyz: (N, 3).
    """
    n = len(_check("label", label, (None,)))
    _check("score", score, (n,))
    _check("xyz", xyz, (n, 3))
    out = []
    for k in range(n_labels):
        sel = label == k
        c = int(sel.sum())
        out.append(LabelSummary(c, float(score[sel].mean()) if c else float("nan"),
                                xyz[sel].mean(axis=0).astype(np.float32) if c else np.full(3, np.nan, np.float32)))
    return out


def apply_min_score(label: np.ndarray, score: np.ndarray, min_score: float) -> np.ndarray:
    """(N,) labels with those whose best score is below ``min_score`` set to −1 (unlabelled)."""
    out = np.asarray(label).astype(np.int32, copy=True)
    out[np.asarray(score) < min_score] = -1
    return out


def label_palette(n_labels: int) -> np.ndarray:
    """(n_labels, 3) uint8 distinct colours (golden-ratio hues); callers draw unlabelled points (−1) grey."""
    hues = (np.arange(n_labels) * 0.618033988749895) % 1.0
    return np.array([[int(40 + 215 * c) for c in colorsys.hsv_to_rgb(h, 0.85, 1.0)] for h in hues],
                    np.uint8).reshape(n_labels, 3)


def subsample(n: int, max_points: int) -> np.ndarray:
    """Indices of at most ``max_points`` of ``n`` points, evenly strided (deterministic)."""
    if max_points <= 0 or n <= max_points:
        return np.arange(n)
    return np.linspace(0, n - 1, max_points).round().astype(np.int64)
