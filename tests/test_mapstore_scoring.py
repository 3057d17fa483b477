"""Scoring with the PCA identity vs brute-force cosine on decoded features; top-k, argmax, regions."""

from __future__ import annotations

from collections import deque

import numpy as np
import pytest
import torch

from services.mapstore.config import RegionParams
from services.mapstore.core.regions import connected_components, find_regions
from services.mapstore.core.index import ScoringIndex
from services.mapstore.core.scoring import PcaBasis, decode_codes

D, K = 48, 8
# the mapstore scores on CUDA where there is one (device auto); nothing but a GPU run shows a host/device mix-up
DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(
    not torch.cuda.is_available(), reason="no CUDA device here (bench/gpu_check.sh runs it on a lent GPU)"))]


def random_basis(rng: np.random.Generator, orthonormal: bool) -> PcaBasis:
    v = rng.normal(size=(K, D))
    if orthonormal:
        v = np.linalg.qr(v.T)[0].T
    return PcaBasis(3, rng.normal(size=D).astype(np.float32), v.astype(np.float32), "test")


def brute_cosine(codes: np.ndarray, basis: PcaBasis, queries: np.ndarray) -> np.ndarray:
    f = decode_codes(codes, basis)
    f /= np.linalg.norm(f, axis=1, keepdims=True)
    q = queries / np.linalg.norm(queries, axis=1, keepdims=True)
    return q @ f.T


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("orthonormal", [True, False])
def test_scores_equal_brute_force_cosine(orthonormal, device):
    rng = np.random.default_rng(0)
    basis = random_basis(rng, orthonormal)
    codes = rng.normal(size=(500, K)).astype(np.float16)
    queries = rng.normal(size=(7, D))
    index = ScoringIndex(codes, basis, device=device)
    np.testing.assert_allclose(index.score(queries), brute_cosine(codes, basis, queries), atol=2e-5)
    np.testing.assert_allclose(index.score(queries[0])[0], brute_cosine(codes, basis, queries[:1])[0], atol=2e-5)


@pytest.mark.parametrize("device", DEVICES)
def test_topk_over_chunks_equals_full_sort(device):
    rng = np.random.default_rng(1)
    basis = random_basis(rng, True)
    codes = rng.normal(size=(1000, K)).astype(np.float32)
    queries = rng.normal(size=(5, D))
    index = ScoringIndex(codes, basis, device=device)
    ref = brute_cosine(codes, basis, queries)
    top = index.topk(queries, k=10, chunk=97)  # blocks smaller than N: exercises the merge
    np.testing.assert_array_equal(top.indices, np.argsort(-ref, axis=1)[:, :10])
    np.testing.assert_allclose(top.scores, np.sort(ref, axis=1)[:, ::-1][:, :10], atol=2e-5)


@pytest.mark.parametrize("device", DEVICES)
def test_argmax_over_labels_equals_brute_force(device):
    rng = np.random.default_rng(2)
    basis = random_basis(rng, False)
    codes = rng.normal(size=(700, K)).astype(np.float32)
    labels = rng.normal(size=(4, D))
    index = ScoringIndex(codes, basis, device=device)
    lab, score = index.argmax(labels, chunk=128)
    ref = brute_cosine(codes, basis, labels)
    np.testing.assert_array_equal(lab, ref.argmax(0))
    np.testing.assert_allclose(score, ref.max(0), atol=2e-5)


def test_shape_errors_are_reported():
    rng = np.random.default_rng(3)
    basis = random_basis(rng, True)
    with pytest.raises(ValueError, match="codes"):
        ScoringIndex(np.zeros((3, K + 1)), basis)
    index = ScoringIndex(np.zeros((3, K)), basis, device="cpu")
    with pytest.raises(ValueError, match="queries"):
        index.score(np.zeros((2, D + 1)))


def bfs_components(ijk: np.ndarray, connectivity: int) -> np.ndarray:
    lookup = {tuple(v): i for i, v in enumerate(ijk.tolist())}
    label = -np.ones(len(ijk), np.int64)
    nxt = 0
    for s in range(len(ijk)):
        if label[s] >= 0:
            continue
        label[s] = nxt
        queue = deque([s])
        while queue:
            i = queue.popleft()
            for d in np.ndindex(3, 3, 3):
                o = np.array(d) - 1
                if not o.any() or (connectivity == 6 and np.abs(o).sum() != 1):
                    continue
                j = lookup.get(tuple(ijk[i] + o))
                if j is not None and label[j] < 0:
                    label[j] = nxt
                    queue.append(j)
        nxt += 1
    return label


@pytest.mark.parametrize("connectivity", [6, 26])
def test_connected_components_match_bfs(connectivity):
    rng = np.random.default_rng(4)
    ijk = np.unique(rng.integers(-6, 6, size=(400, 3)), axis=0)
    got = connected_components(ijk, connectivity)
    ref = bfs_components(ijk, connectivity)
    # same partition: labels correspond one to one
    pairs = set(zip(got.tolist(), ref.tolist()))
    assert len(pairs) == len(set(got.tolist())) == len(set(ref.tolist()))


def test_regions_are_connected_high_score_blobs_with_boxes():
    a = np.array([[x, y, z] for x in range(3) for y in range(2) for z in range(2)])  # 12 voxels
    b = a + [10, 0, 0]
    noise = np.array([[5, 5, 5]])  # one isolated high voxel: below min_voxels
    low = a + [0, 5, 0]
    ijk = np.concatenate([a, b, noise, low])
    xyz = (ijk + 0.5) * 0.1
    scores = np.r_[np.full(12, 0.9), np.full(12, 0.7), 0.95, np.full(12, 0.1)]
    regions = find_regions(ijk, xyz, scores, RegionParams(score_threshold=0.5, min_voxels=2))
    assert [r.count for r in regions] == [12, 12]
    assert regions[0].score == pytest.approx(0.9) and regions[1].score == pytest.approx(0.7)
    np.testing.assert_allclose(regions[0].box_min, [0.05, 0.05, 0.05])
    np.testing.assert_allclose(regions[0].box_max, [0.25, 0.15, 0.15])
    np.testing.assert_allclose(regions[1].centroid, xyz[12:24].mean(0))
    np.testing.assert_array_equal(np.sort(regions[1].indices), np.arange(12, 24))
