"""The fast query paths against exact dense references: one-pass scoring, top-k from the points above the
threshold, regions from those points only, the table neighbour search, and the mapstore's answer cache (which
must never outlive the map revision it was computed on)."""

from __future__ import annotations

import dataclasses
from collections import deque

import numpy as np
import pytest

from services.common.schema import MapQuery, decode
from services.mapstore import queries
from services.mapstore.config import RegionParams
from services.mapstore.core import regions as regions_mod
from services.mapstore.core.regions import connected_components, find_regions, regions_of
from services.mapstore.core.index import ScoringIndex
from services.mapstore.core.scoring import PcaBasis, best_of, decode_codes
from services.mapstore.service import handle
from services.mapstore.state import MapState
from tests.test_mapstore_service import STREAM, settings, stream_messages


def dense_cosine(codes: np.ndarray, basis: PcaBasis, queries_: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """(Q, N) float64 cosine of the decoded features, NaN where a point has no code."""
    f = decode_codes(np.where(valid[:, None], codes, 0.0), basis)
    t = queries_.astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):  # a point without a code may decode to 0 (zero mean)
        s = (t @ f.T) / np.linalg.norm(t, axis=1)[:, None] / np.linalg.norm(f, axis=1)[None]
    s[:, ~valid] = np.nan
    return s


def random_index(n: int = 400, k: int = 6, d: int = 20, seed: int = 0):
    rng = np.random.default_rng(seed)
    basis = PcaBasis(1, rng.normal(size=d).astype(np.float32),
                     np.linalg.qr(rng.normal(size=(d, k)))[0].T.astype(np.float32))
    codes = rng.normal(size=(n, k)).astype(np.float32)
    valid = rng.random(n) > 0.1
    return ScoringIndex(codes, basis, "cpu", valid=valid), codes, basis, valid, rng


def test_score_is_exact_cosine_with_nan_for_points_without_code():
    index, codes, basis, valid, rng = random_index()
    q = rng.normal(size=(3, basis.dim)).astype(np.float32)
    s = index.score(q)
    np.testing.assert_allclose(s, dense_cosine(codes, basis, q, valid), atol=2e-5)
    assert np.isnan(s[:, ~valid]).all() and np.isfinite(s[:, valid]).all()
    np.testing.assert_allclose(index.score(q[1])[0], s[1], atol=1e-6, equal_nan=True)  # one vector alone
    s[0, 0] = 7.0  # a fresh array: writing to it changes nothing in the index
    assert index.score(q[:1])[0, 0] != 7.0


@pytest.mark.parametrize("k", [1, 5, 40, 450, 1000])  # 450: more than the finite scores, fewer than all
def test_best_of_matches_a_full_sort(k):
    rng = np.random.default_rng(k)
    s = rng.normal(size=500).astype(np.float32)
    s[rng.random(500) < 0.2] = np.nan
    finite = np.flatnonzero(np.isfinite(s))
    ref = finite[np.argsort(-s[finite], kind="stable")][:k]
    idx, best = best_of(s, k)
    np.testing.assert_array_equal(idx, ref)
    np.testing.assert_array_equal(best, s[ref])
    for cut in (0.0, 1.0, 2.5):  # a pool holding every point above a cut: used when it has k, else ignored
        pool = np.flatnonzero(s >= cut)
        idx, best = best_of(s, k, above=pool)
        np.testing.assert_array_equal(idx, ref)


def test_best_of_breaks_ties_by_index():
    s = np.array([0.5, 0.9, 0.5, 0.9, np.nan, 0.5], np.float32)
    np.testing.assert_array_equal(best_of(s, 4)[0], [1, 3, 0, 2])


def bfs_components(ijk: np.ndarray) -> np.ndarray:
    """Reference 26-connected labels by breadth-first search, numbered in order of each component's first voxel."""
    where = {tuple(v): i for i, v in enumerate(ijk.tolist())}
    label = np.full(len(ijk), -1)
    steps = [(a, b, c) for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1) if (a, b, c) != (0, 0, 0)]
    n = 0
    for start in range(len(ijk)):
        if label[start] >= 0:
            continue
        label[start], todo = n, deque([start])
        while todo:
            v = ijk[todo.popleft()]
            for st in steps:
                j = where.get((v[0] + st[0], v[1] + st[1], v[2] + st[2]))
                if j is not None and label[j] < 0:
                    label[j] = n
                    todo.append(j)
        n += 1
    return label


@pytest.mark.parametrize("spread", [6, 40, 200_000])  # dense, sparse, and a box too big for the table
def test_connected_components_table_and_search_agree_with_bfs(spread, monkeypatch):
    rng = np.random.default_rng(spread)
    ijk = np.unique(rng.integers(-spread, spread, size=(300, 3)), axis=0)
    ijk = ijk[rng.permutation(len(ijk))]
    ref = bfs_components(ijk)
    np.testing.assert_array_equal(connected_components(ijk, 26), ref)
    monkeypatch.setattr(regions_mod, "TABLE_MAX_CELLS", 0)  # force the sorted-key search
    np.testing.assert_array_equal(connected_components(ijk, 26), ref)


def test_regions_of_equals_find_regions():
    rng = np.random.default_rng(3)
    ijk = np.unique(rng.integers(0, 12, size=(900, 3)), axis=0)
    xyz = ijk * 0.05 + rng.normal(scale=0.01, size=ijk.shape)
    scores = rng.random(len(ijk)).astype(np.float32)
    params = RegionParams(score_threshold=0.6, min_voxels=2, max_regions=7)
    sel = np.flatnonzero(scores >= 0.6)
    got, ref = regions_of(ijk, xyz, sel, scores[sel], params), find_regions(ijk, xyz, scores, params)
    assert [r.count for r in got] == [r.count for r in ref] and len(ref) > 1
    for a, b in zip(got, ref):
        assert a.score == b.score and a.score_max == b.score_max
        np.testing.assert_array_equal(a.indices, b.indices)
        np.testing.assert_array_equal(a.centroid, b.centroid)


def build_state(tmp_path, n_keyframes: int):
    """A real MapState fed a synthetic stream; the third keyframe's codes never come (voxels without codes)."""
    cfg = settings(tmp_path)
    state = MapState(cfg)
    msgs = stream_messages(n_keyframes)
    for i, msg in enumerate(msgs):
        if type(msg).__name__ == "Keyframe" and msg.seq == 4:
            msg = dataclasses.replace(msg, codes=None, pca_version=-1)
        handle(state, msg, cfg)
    return state, cfg, msgs


def reference_answer(state: MapState, vectors: np.ndarray, top_k: int, max_regions: int):
    """Per vector: (regions by find_regions on dense decoded cosines, top-k scores), all from scratch."""
    fused, basis = state.map.fused(), state.basis()
    valid = np.ones(len(fused.keys), bool) if fused.code_weight is None else fused.code_weight > 0
    s = dense_cosine(np.nan_to_num(fused.codes), basis, vectors, valid)
    params = state.map.params.regions
    out = []
    for row in s:
        thr = params.relative_threshold * np.nanmax(row)
        regs = find_regions(fused.ijk, fused.xyz, row, dataclasses.replace(params, score_threshold=thr,
                                                                            max_regions=max_regions))
        finite = np.flatnonzero(np.isfinite(row))
        out.append((regs, np.sort(row[finite])[::-1][:top_k]))
    return out, valid


def ask(state: MapState, vectors: np.ndarray, seq: int = 1):
    q = MapQuery(STREAM, seq, 0, vectors=vectors.astype(np.float32), space="oracle", top_k=6, max_regions=4)
    return decode(queries.answer(state, STREAM, f"kmvipe/{STREAM}/map/query", {}, q.encode()))


def check_against_reference(state: MapState, vectors: np.ndarray, ans) -> None:
    ref, valid = reference_answer(state, vectors, 6, 4)
    assert not valid.all()  # the keyframe without codes left voxels without codes
    fused = state.map.fused()
    for qi, (regs, top) in enumerate(ref):
        mine = ans.region_query == qi
        assert list(ans.region_count[mine]) == [r.count for r in regs]
        np.testing.assert_allclose(ans.region_score[mine], [r.score for r in regs], atol=1e-4)
        np.testing.assert_allclose(ans.region_centroid[mine].reshape(-1, 3),
                                   np.array([r.centroid for r in regs]).reshape(-1, 3), atol=1e-4)
        pts = ans.point_query == qi
        np.testing.assert_allclose(ans.point_score[pts], top, atol=1e-4)
        # top points are points with codes: their positions are voxels of the map that have one
        hit = (np.abs(fused.xyz[valid][None] - ans.point_xyz[pts][:, None]).max(-1) < 1e-4).any(1)
        assert hit.all()


def test_query_answers_as_the_dense_reference_and_the_cache_follows_the_map(tmp_path):
    state, cfg, msgs = build_state(tmp_path, 4)
    basis = state.basis()
    rng = np.random.default_rng(5)
    vectors = basis.mean + rng.normal(size=(3, basis.rank)).astype(np.float32) @ basis.components
    first = ask(state, vectors)
    assert len(first.region_score) > 0
    check_against_reference(state, vectors, first)
    again = ask(state, vectors[1:2], seq=2)  # one of the vectors again: from the cache, the same numbers
    assert again.seq == 2
    np.testing.assert_array_equal(again.point_score, first.point_score[first.point_query == 1])
    np.testing.assert_array_equal(again.region_centroid, first.region_centroid[first.region_query == 1])
    revision = state.map.revision
    more = stream_messages(6)  # two more keyframes: a new map revision, so no cached answer may be reused
    for msg in more[len(msgs) - 1:]:
        handle(state, msg, cfg)
    assert state.map.revision != revision
    check_against_reference(state, vectors, ask(state, vectors, seq=3))
