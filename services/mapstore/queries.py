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

import numpy as np

from services.common.schema import MapAnswer, MapChunk, MapQuery, MapSegment, MapStats, Poses, decode
from services.mapstore.core.regions import find_regions
from services.mapstore.state import MapState

DEFAULT_CHUNK = 100_000
MAX_CHUNK = 1_000_000  # a bigger chunk would exceed what a single reply should carry


def _basis_space(state: MapState) -> str:
    return state.bases[max(state.bases)].backbone if state.bases else ""


def _check_space(state: MapState, q: MapQuery) -> None:
    space = _basis_space(state)
    if q.space and space and q.space != space:
        raise ValueError(f"query vectors are in '{q.space}' but this map's features are in '{space}'")


def query(state: MapState, q: MapQuery) -> MapAnswer:
    _check_space(state, q)
    index = state.index()
    fused = state.map.fused()
    scores = index.score(q.vectors)
    top = index.topk(q.vectors, q.top_k) if index.n_valid else None
    params = state.map.params.regions
    rows: list[tuple] = []
    for qi, s in enumerate(scores):
        threshold = q.threshold
        if threshold < 0:
            scored = s[np.isfinite(s)]  # voxels without codes (NaN) take no part
            threshold = params.score_threshold
            if params.relative_threshold > 0 and scored.size:
                threshold = params.relative_threshold * float(scored.max())
        found = find_regions(fused.ijk, fused.xyz, s, dataclasses.replace(params, score_threshold=threshold,
                                                                          max_regions=q.max_regions))
        rows += [(qi, r.score, r.centroid, r.box_min, r.box_max, r.count) for r in found]
    f4 = lambda values, shape: np.asarray(values, np.float32).reshape(shape)  # noqa: E731
    n_top = 0 if top is None else top.indices.shape[1]
    return MapAnswer(
        q.stream, q.seq, time.time_ns(),
        region_query=np.array([r[0] for r in rows], np.int32), region_score=f4([r[1] for r in rows], (-1,)),
        region_centroid=f4([r[2] for r in rows], (-1, 3)), region_box_min=f4([r[3] for r in rows], (-1, 3)),
        region_box_max=f4([r[4] for r in rows], (-1, 3)), region_count=np.array([r[5] for r in rows], np.int32),
        point_query=np.repeat(np.arange(len(scores), dtype=np.int32), n_top),
        point_xyz=f4(fused.xyz[top.indices.ravel()] if top is not None else [], (-1, 3)),
        point_score=f4(top.scores.ravel() if top is not None else [], (-1,)),
        all_scores=scores.astype(np.float32) if q.with_points else None, n_points=int(len(fused.keys)),
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


def answer(state: MapState, stream: str, key: str, params: dict, payload: bytes | None) -> bytes:
    """Dispatch one query on ``.../map/<verb>`` (the ``Bus.serve`` handler); errors become error replies."""
    verb = key.rsplit("/", 1)[-1]
    with state.lock:
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
    raise KeyError(f"unknown map verb {verb!r}; known: query, segment, export, stats, trajectory")
