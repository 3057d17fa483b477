"""Queryables under ``kmvipe/<s>/map/<verb>``, speaking the wire messages of services/common/schema.py.

| verb | request | reply |
|---|---|---|
| query | ``MapQuery`` payload | ``MapAnswer``: regions (connected voxels above a threshold) and top-k points per vector |
| segment | ``MapQuery`` payload (the vectors are the label set) | ``MapSegment``: per-point argmax label and score |
| export | selector ``?chunk=i;chunk_size=n`` | ``MapChunk`` i of the fused map |
| stats | — | ``MapStats`` |
| trajectory | — | ``Poses``: every frame's latest pose (mapping's revisions over tracking's), by seq |

Voxels that only keyframes whose codes have not arrived saw have no code: they are absent from scoring (NaN in
``all_scores`` and ``MapSegment.score``, label −1, never a top point or in a region), not scored as the zero code.
"""

from __future__ import annotations

import dataclasses
import time
from typing import NamedTuple

import numpy as np

from services.common.schema import MapAnswer, MapChunk, MapQuery, MapSegment, MapStats, Poses, decode
from services.mapstore.config import RegionParams
from services.mapstore.core.regions import regions_of
from services.mapstore.core.scoring import best_of
from services.mapstore.state import MapState

DEFAULT_CHUNK = 100_000
MAX_CHUNK = 1_000_000  # a bigger chunk would exceed what a single reply should carry


def _basis_space(state: MapState) -> str:
    return state.bases[max(state.bases)].backbone if state.bases else ""


def _check_space(state: MapState, q: MapQuery) -> None:
    space = _basis_space(state)
    if q.space and space and q.space != space:
        raise ValueError(f"query vectors are in '{q.space}' but this map's features are in '{space}'")


class _Found(NamedTuple):
    """What one query vector found: its regions (without their voxel lists, which the answer does not carry)
    and its top points (indices into the fused map)."""

    regions: list[tuple[float, np.ndarray, np.ndarray, np.ndarray, int]]  # score, centroid, box min/max, count
    top_idx: np.ndarray  # (k,) int64, best first
    top_score: np.ndarray  # (k,) float32


def query(state: MapState, q: MapQuery) -> MapAnswer:
    """Regions and top points of each query vector (the ``map/query`` verb); the caller holds ``state.lock``.

    The vectors not answered from the cache are scored together, once against every point (exact cosine, see
    ScoringIndex); each one's threshold, top points and regions are then taken from its score vector, reading
    only the points above the threshold. A vector asked again (same options) on the same map revision is
    answered from ``state.answers`` (``MapstoreSettings.answer_cache`` vectors).
    """
    _check_space(state, q)
    index = state.index()
    fused = state.map.fused()
    params = dataclasses.replace(state.map.params.regions, max_regions=q.max_regions)
    vectors = np.ascontiguousarray(q.vectors, np.float32)
    keys = [None if q.with_points else (v.tobytes(), q.space, q.top_k, q.threshold, params) for v in vectors]
    found: list[_Found | None] = [state.answers.get(index, key) for key in keys]
    todo = [i for i, f in enumerate(found) if f is None]
    all_scores = None
    if todo:
        scores = index.score(vectors[todo])
        k = min(q.top_k, index.n_valid)
        for i, s in zip(todo, scores):
            sel = np.flatnonzero(s >= _threshold(s, q.threshold, params))  # NaN (no code) is never selected
            regions = [(r.score, r.centroid, r.box_min, r.box_max, r.count)
                       for r in regions_of(fused.ijk, fused.xyz, sel, s[sel], params)]
            found[i] = _Found(regions, *best_of(s, k, above=sel))
            state.answers.put(index, keys[i], found[i])
        all_scores = scores if q.with_points else None  # with_points: every vector is in todo
    return _answer(q, fused, found, all_scores)


def _threshold(s: np.ndarray, asked: float, params: RegionParams) -> float:
    """The region threshold of one score vector: the query's, else relative to the best finite score."""
    if asked >= 0:
        return asked
    best = float(np.fmax.reduce(s)) if s.size else float("nan")  # fmax skips NaN (points without codes)
    if params.relative_threshold > 0 and np.isfinite(best):
        return params.relative_threshold * best
    return params.score_threshold


def _answer(q: MapQuery, fused, found: list[_Found], all_scores: np.ndarray | None) -> MapAnswer:
    rows = [(qi, r) for qi, f in enumerate(found) for r in f.regions]
    f4 = lambda values, shape: np.asarray(values, np.float32).reshape(shape)  # noqa: E731
    idx = np.concatenate([f.top_idx for f in found]) if found else np.zeros(0, np.int64)
    return MapAnswer(
        q.stream, q.seq, time.time_ns(),
        region_query=np.array([qi for qi, _ in rows], np.int32), region_score=f4([r[0] for _, r in rows], (-1,)),
        region_centroid=f4([r[1] for _, r in rows], (-1, 3)), region_box_min=f4([r[2] for _, r in rows], (-1, 3)),
        region_box_max=f4([r[3] for _, r in rows], (-1, 3)), region_count=np.array([r[4] for _, r in rows], np.int32),
        point_query=np.repeat(np.arange(len(found), dtype=np.int32), [len(f.top_idx) for f in found]),
        point_xyz=f4(np.take(fused.xyz, idx, axis=0), (-1, 3)),
        point_score=f4(np.concatenate([f.top_score for f in found]) if found else [], (-1,)),
        all_scores=all_scores, n_points=int(len(fused.keys)),
    )


def segment(state: MapState, q: MapQuery) -> MapSegment:
    _check_space(state, q)
    label, best = state.index().argmax(q.vectors)
    return MapSegment(q.stream, q.seq, time.time_ns(), xyz=state.map.fused().xyz.astype(np.float32),
                      label=np.asarray(label, np.int32), score=np.asarray(best, np.float32))


def export(state: MapState, stream: str, chunk: int, size: int) -> MapChunk:
    if not 0 < size <= MAX_CHUNK or chunk < 0:
        raise ValueError(f"chunk must be >= 0 and chunk_size in 1..{MAX_CHUNK}")
    fused = state.map.fused()
    n = len(fused.keys)
    sl = slice(chunk * size, (chunk + 1) * size)
    return MapChunk(stream, chunk, time.time_ns(), xyz=fused.xyz[sl].astype(np.float32),
                    rgb=np.asarray(fused.colours[sl], np.uint8), codes=fused.codes[sl].astype(np.float16),
                    n_chunks=max(1, -(-n // size)), total_points=n)


def stats(state: MapState, stream: str) -> MapStats:
    fused = state.map.fused()
    return MapStats(stream, state.map.revision, time.time_ns(), keyframes=state.keyframe_count(),
                    points=int(len(fused.keys)), voxels=int(len(fused.keys)), backbone=_basis_space(state),
                    pca_version=max(state.bases) if state.bases else -1, metric=bool(state.metric),
                    keyframes_without_codes=state.without_codes_count(), session=state.session)


FUSED_MAP_VERBS = ("query", "segment", "export", "stats", "example")  # answered from the fused map


def answer(state: MapState, stream: str, key: str, params: dict, payload: bytes | None) -> bytes:
    """Dispatch one query on ``.../map/<verb>`` (the ``Bus.serve`` handler); errors become error replies."""
    verb = key.rsplit("/", 1)[-1]
    with state.lock:
        if verb in FUSED_MAP_VERBS:  # committed but not re-fused yet (refresh_period_s): answered on it too
            state.refresh()
        if verb in ("query", "segment"):
            q = decode(payload or b"", MapQuery)
            return (query(state, q) if verb == "query" else segment(state, q)).encode()
        if verb == "export":
            return export(state, stream, int(params.get("chunk", 0)), int(params.get("chunk_size", DEFAULT_CHUNK))).encode()
        if verb == "stats":
            return stats(state, stream).encode()
    if verb == "trajectory":  # outside the map's lock: it reads the database only
        seqs, stamps, poses = state.trajectory()
        return Poses(stream, len(seqs), time.time_ns(), frame_seqs=seqs, stamps_ns=stamps, poses=poses,
                     session=state.session).encode()
    from services.mapstore import keyframe_queries  # here: it builds on this module's `query`

    if verb in keyframe_queries.VERBS:  # thumbnails and query by keyframe region; they take the lock themselves
        return keyframe_queries.answer(state, stream, verb, params, payload)
    raise KeyError(f"unknown map verb {verb!r}; known: query, segment, export, stats, trajectory, "
                   f"{', '.join(keyframe_queries.VERBS)}")
