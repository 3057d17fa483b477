"""Regions: connected components of voxels whose score is above a threshold."""

from __future__ import annotations

from dataclasses import dataclass
from itertools import product

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components as csgraph_components

from services.mapstore.config import RegionParams
from services.mapstore.core.fusion import voxel_keys


@dataclass(frozen=True)
class Region:
    """A connected set of high-scoring voxels.

    Fields: centroid (3,) float64 world (mean of the voxel points); box_min, box_max (3,)
    float64 axis-aligned bounds of the voxel points; score: mean score; score_max: best score;
    count: number of voxels; indices: (count,) int64 indices into the scored point arrays.
    """

    centroid: np.ndarray
    box_min: np.ndarray
    box_max: np.ndarray
    score: float
    score_max: float
    count: int
    indices: np.ndarray


def _offsets(connectivity: int) -> np.ndarray:
    """Half of the neighbour offsets (the other half is symmetric), (n, 3) int64."""
    all_offsets = [o for o in product((-1, 0, 1), repeat=3) if any(o)]
    if connectivity == 6:
        all_offsets = [o for o in all_offsets if sum(map(abs, o)) == 1]
    elif connectivity != 26:
        raise ValueError(f"connectivity must be 6 or 26, got {connectivity}")
    return np.array([o for o in all_offsets if o > (0, 0, 0)], dtype=np.int64)


def connected_components(ijk: np.ndarray, connectivity: int = 26) -> np.ndarray:
    """Label connected voxels.

    Args:
        ijk: (N, 3) int64 distinct voxel coordinates.
        connectivity: 6 or 26.
    Returns:
        (N,) int64 component label per voxel, labels 0..C−1.
    """
    n = ijk.shape[0]
    keys = voxel_keys(ijk)
    order = np.argsort(keys)
    sorted_keys = keys[order]
    src, dst = [], []
    for off in _offsets(connectivity):
        # packing is additive, so the neighbours' keys are the sorted keys shifted by a constant: sorted needles
        # make searchsorted cache-friendly (5-10x faster than looking up unsorted neighbour keys)
        delta = int(voxel_keys(off[None])[0] - voxel_keys(np.zeros((1, 3), np.int64))[0])
        nk = sorted_keys + delta
        pos = np.clip(np.searchsorted(sorted_keys, nk), 0, max(n - 1, 0))
        hit = np.flatnonzero(sorted_keys[pos] == nk) if n else np.zeros(0, np.int64)
        src.append(order[hit])
        dst.append(order[pos[hit]])
    a = np.concatenate(src) if src else np.zeros(0, np.int64)
    b = np.concatenate(dst) if dst else np.zeros(0, np.int64)
    # scipy's union-find over the neighbour graph: ~20x faster than label propagation with ufunc.at
    graph = coo_matrix((np.ones(len(a), np.int8), (a, b)), shape=(n, n)).tocsr()
    _, label = csgraph_components(graph, directed=False)
    return label.astype(np.int64)


def find_regions(
    ijk: np.ndarray, xyz: np.ndarray, scores: np.ndarray, params: RegionParams
) -> list[Region]:
    """Cluster voxels scoring at least `params.score_threshold` into connected regions.

    Args:
        ijk: (N, 3) int64 voxel coordinates of the map points.
        xyz: (N, 3) float world positions of the map points.
        scores: (N,) float scores of one query.
        params: threshold, connectivity, minimum size, maximum number.
    Returns:
        Regions sorted by mean score, best first (at most params.max_regions).
    """
    if not (ijk.shape[0] == xyz.shape[0] == scores.shape[0]):
        raise ValueError("ijk, xyz and scores must have the same length")
    sel = np.flatnonzero(scores >= params.score_threshold)
    if sel.size == 0:
        return []
    labels = connected_components(ijk[sel], params.connectivity)
    # per-component statistics in one pass (reduceat over label-sorted points), no loop over components
    order = np.argsort(labels, kind="stable")
    counts = np.bincount(labels)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    p, sc = xyz[sel[order]], scores[sel[order]]
    mean_score = np.add.reduceat(sc, starts) / counts
    ranked = [c for c in np.argsort(-mean_score, kind="stable") if counts[c] >= params.min_voxels]
    ranked = ranked[: params.max_regions]
    if not ranked:
        return []
    box_min, box_max = np.minimum.reduceat(p, starts, axis=0), np.maximum.reduceat(p, starts, axis=0)
    centroid = np.add.reduceat(p, starts, axis=0) / counts[:, None]
    best = np.maximum.reduceat(sc, starts)
    return [
        Region(centroid[c], box_min[c], box_max[c], float(mean_score[c]), float(best[c]), int(counts[c]),
               sel[order[starts[c]: starts[c] + counts[c]]])
        for c in ranked
    ]
