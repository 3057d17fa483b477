"""Flat mapstore memory: keyframes that have left ba's graph are folded into frozen voxel sums and leave memory.

The scene (tests/helpers/carving_scene.py): a camera sliding along a wall with a box in front that moves half way
through, so carving is at work; ba is imitated the way it behaves: its graph holds the newest ``KEEP`` keyframes
(revising the newest poses every time), now and then drops a redundant one from the middle, and never names a
keyframe again once it has left. The folded map must equal the map without folding, stay bounded in memory,
survive a restart, and follow a new PCA basis. Here the map's core; through the service state:
tests/test_mapstore_folding_policy.py.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from services.common.schema import PcaBasis as PcaMessage
from services.common.pca_codes import code_map, convert_codes
from services.mapstore.config import CarvingParams, FusionParams, MapParams
from services.mapstore.core.frozen import FrozenSums
from services.mapstore.core.fusion import make_contribution, merge_contributions
from services.mapstore.frozen_files import FileSums
from services.mapstore.core.map import KeyframeMap, code_maps_to_latest
from services.mapstore.core.scoring import PcaBasis
from tests.helpers.carving_scene import BOX, CHAIR, MOVED_BOX, add_keyframe, cam_pose, cell_labels, label_codes, render

STREAM, D, K = "mem0", 16, 8
KEEP = 40  # ba's keep_keyframes
REVISED = 2  # the newest keyframes whose poses each graph revises
DROP_EVERY = 23  # every so often ba drops a redundant keyframe from the middle of its window
COMPONENTS = np.linalg.qr(np.random.default_rng(3).normal(size=(D, D)))[0][:K]  # (K, D) orthonormal rows


def basis(version: int) -> PcaMessage:
    """Version 1: the codes' own basis; later versions rotate it within its subspace and move its mean."""
    rng = np.random.default_rng(version)
    rot = np.linalg.qr(rng.normal(size=(K, K)))[0] if version > 1 else np.eye(K)
    mean = np.zeros(D) if version == 1 else 0.05 * rng.normal(size=K) @ COMPONENTS
    return PcaMessage(STREAM, 0, 0, version=version, backbone="oracle", mean=mean.astype(np.float32),
                      components=(rot @ COMPONENTS).astype(np.float32))


def camera_x(i: int) -> float:
    return 1.2 * np.sin(0.07 * i)


def keyframe_data(i: int, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(truth pose, disparity (H, W), codes (H, W, K) in basis 1) of keyframe i of an n-keyframe stream."""
    pose = cam_pose(camera_x(i))
    box = BOX if i < n // 2 else MOVED_BOX
    disparity, which = render(pose, [box])
    return pose, disparity, label_codes(cell_labels(which, [CHAIR]), seed=i)


def revised(pose: np.ndarray, kf: int, step: int) -> np.ndarray:
    """BA's estimate of keyframe kf's pose at graph ``step``: it still moves while kf is among the newest."""
    out = pose.copy()
    out[0, 3] += 0.002 * min(step - kf, REVISED)
    return out


class Ba:
    """Which keyframes ba holds: the newest KEEP, minus the redundant ones it dropped from the middle."""

    def __init__(self) -> None:
        self.window: list[int] = []

    def add(self, i: int) -> list[int]:
        self.window.append(i)
        if len(self.window) > KEEP:
            self.window.pop(0)
        if i and i % DROP_EVERY == 0:
            self.window.pop(len(self.window) // 2)
        return list(self.window)


# ----- the core ---------------------------------------------------------------------------------------------
UNSNAPPED = MapParams(fusion=FusionParams(fold_snap_voxels=0.0))  # folding alone changes nothing in the map


def build_core(n: int, fold: bool, params: MapParams = UNSNAPPED) -> tuple[KeyframeMap, int, int]:
    """The map of an n-keyframe stream fed as ba sends it; (map, most keyframes held live at once, cells of the
    folded keyframes that later views carved)."""
    m = KeyframeMap(params, voxel_size=0.1)
    ba, truth, most_live, carved = Ba(), {}, 0, 0
    for i in range(n):
        pose, disparity, codes = keyframe_data(i, n)
        truth[i] = pose
        add_keyframe(m, i, revised(pose, i, i), disparity, codes)
        window = ba.add(i)
        for k in window:
            m.set_pose(k, revised(truth[k], k, i))
        m.refresh()
        if fold:
            held = set(window)
            ids = m.foldable(lambda k: k not in held and k < window[-1])
            carved += sum(m._carved[k].size for k in ids if k in m._carved)  # what carving took from them
            m.fold(ids)
        most_live = max(most_live, len(m.live))
    return m, most_live, carved


def assert_same_fused(a, b, codes_atol: float = 1e-5) -> None:
    assert len(a.keys) > 100
    np.testing.assert_array_equal(a.keys, b.keys)
    np.testing.assert_allclose(a.xyz, b.xyz, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(a.colours, b.colours)
    np.testing.assert_allclose(a.weight, b.weight, rtol=1e-12)
    np.testing.assert_array_equal(a.count, b.count)
    np.testing.assert_allclose(a.codes, b.codes, rtol=0, atol=codes_atol)


def test_the_folded_map_equals_the_map_without_folding_and_holds_a_bounded_window():
    n = 120
    folded, most_live, carved = build_core(n, fold=True)
    whole, _, _ = build_core(n, fold=False)
    assert folded.folded_count > n - KEEP - folded.fold_window - 5
    assert most_live <= KEEP + folded.fold_window + 2
    assert len(folded.contents) == len(folded.live) <= KEEP + folded.fold_window + 2
    assert len(whole.contents) == n
    # the box's old place is carved from the keyframes whose carving window reaches past the move (before they
    # fold), as without folding; the fused maps agree voxel for voxel
    assert carved > 100
    assert_same_fused(folded.fused(), whole.fused())


def test_folding_waits_for_a_keyframe_that_is_not_settled():
    n = 60
    m = KeyframeMap(MapParams(), voxel_size=0.1)
    for i in range(n):
        pose, disparity, codes = keyframe_data(i, n)
        add_keyframe(m, i, pose, disparity, codes)
    m.refresh()
    window = m.fold_window
    assert m.foldable(lambda k: k != 40) == list(range(40 - window))  # in order; its window must be settled too
    assert m.foldable(lambda k: k != 5) == []  # keyframe 0's window holds an unsettled keyframe
    m.fold(list(range(10)))
    assert m.live == list(range(10, n)) and m.folded_upto == 9 and m.folded_count == 10
    assert sorted(m.depths) == [8, 9] + list(range(10, n))  # the ghosts: consistency neighbours of keyframe 10
    m.set_pose(59, cam_pose(0.5))
    assert m.foldable(lambda k: True) == []  # a refresh is due: only up-to-date contributions fold
    with pytest.raises(ValueError):
        m.fold([0])


@pytest.mark.parametrize("in_files", [False, True], ids=["memory", "files"])
def test_frozen_sums_of_old_pca_versions_are_carried_in_the_current_one(in_files, tmp_path, monkeypatch):
    """Refits must not multiply the frozen sums: beyond ``frozen_versions`` an old version's sums are converted into
    the current version (these bases share one subspace, so even the extra projection is exact). The same with the
    sums in files, read and merged in chunks far smaller than a version's sums."""
    monkeypatch.setattr(FrozenSums, "chunk_rows", 97)
    n = 90
    bases = {v: PcaBasis(v, np.asarray(basis(v).mean, np.float64), np.asarray(basis(v).components, np.float64),
                         "oracle") for v in (1, 2, 3)}
    params = dataclasses.replace(UNSNAPPED, carving=CarvingParams(semantic=False))  # carving of old points is not
    # re-judged: keep it out

    def build(fold: bool) -> KeyframeMap:
        store = FileSums(tmp_path / f"{fold}.db") if in_files else None
        m = KeyframeMap(params, voxel_size=0.1, versioned=True, frozen_versions=1, frozen_store=store)
        known: dict[int, PcaBasis] = {}
        for i in range(n):
            version = 1 + 3 * i // n  # a refit after each third of the stream
            if version not in known:
                known[version] = bases[version]
                m.set_code_space(*code_maps_to_latest(known))
            pose, disparity, codes = keyframe_data(i, n)
            coded = convert_codes(codes, code_map(bases[1], bases[version])).astype(np.float16)
            add_keyframe(m, i, pose, disparity, coded, version)
            m.refresh()
            if fold:
                m.fold(m.foldable(lambda k: k < i - 20))
        return m

    capped, whole = build(True), build(False)
    assert capped.folded_count > 40 and set(capped._frozen) == {3}  # versions 1 and 2 carried in 3
    assert len(capped._frozen[3]) > 3 * FrozenSums.chunk_rows  # read and merged in several chunks
    assert_same_fused(capped.fused(), whole.fused(), codes_atol=1e-4)


@pytest.mark.parametrize("in_files", [False, True], ids=["memory", "files"])
@pytest.mark.parametrize("chunk_rows", [7, 16384])
def test_frozen_sums_merge_to_the_sum_of_their_parts(in_files, chunk_rows, tmp_path):
    rng = np.random.default_rng(0)
    parts = [make_contribution(rng.normal(size=(50, 3)), rng.uniform(0.1, 1, 50),
                               rng.normal(size=(50, K)).astype(np.float16), rng.integers(0, 255, (50, 3)), 0.5)
             for _ in range(30)]
    store = FileSums(tmp_path / "map.db") if in_files else None
    frozen = FrozenSums(store, min_pending=120, chunk_rows=chunk_rows)
    for p in parts:
        frozen.add(p)
    chunks = list(frozen)
    assert max(c.keys.size for c in chunks) <= chunk_rows
    got, want = frozen.contribution(), merge_contributions(parts)
    np.testing.assert_array_equal(got.keys, want.keys)  # ascending and distinct across chunks too
    np.testing.assert_allclose(got.weight, want.weight)
    np.testing.assert_allclose(got.xyz, want.xyz)
    np.testing.assert_allclose(got.codes, want.codes, atol=1e-4)
    np.testing.assert_allclose(got.colours, want.colours, rtol=1e-5)
    np.testing.assert_array_equal(got.count, want.count)
    assert len(frozen) == want.keys.size
    assert (frozen.nbytes_in_memory == 0) == in_files  # merged: in files nothing stays in memory
    if in_files:
        frozen.discard()
        assert not any(store.folder.iterdir())  # runs discarded with their files


def _sums_point_by_point(parts, cmaps=None):
    """Ground truth: every row of every part added into its voxel one at a time in float64 (codes through each
    part's map into the new version where ``cmaps`` are given)."""
    sums: dict[int, list] = {}
    for i, p in enumerate(parts):
        codes = p.codes.astype(np.float64)
        if cmaps is not None and cmaps[i] is not None:
            codes = codes @ cmaps[i].matrix.T + p.weight[:, None] * cmaps[i].offset
        for r, key in enumerate(p.keys.tolist()):
            s = sums.setdefault(key, [0.0, np.zeros(3), np.zeros(codes.shape[1]), np.zeros(3), 0])
            s[0] += p.weight[r]
            s[1] += p.xyz[r]
            s[2] += codes[r]
            s[3] += p.colours[r]
            s[4] += int(p.count[r])
    keys = np.array(sorted(sums))
    return keys, [np.array([sums[k][f] for k in keys.tolist()]) for f in range(5)]


def _random_parts(rng, n_parts: int, k: int, rows: int = 2000, voxel: float = 0.1):
    points = [rng.uniform(-1, 1, (rows, 3)) for _ in range(n_parts)]
    return [make_contribution(p, rng.uniform(0.1, 1, rows), rng.normal(size=(rows, k)).astype(np.float32),
                              rng.integers(0, 255, (rows, 3)), voxel) for p in points]


def test_voxel_sums_a_few_columns_at_a_time_equal_sums_point_by_point():
    """Keyframe contributions and their merge sum their rows a few columns at a time (fusion.SUM_COLUMNS): the
    sums equal every point added into its voxel one by one, a code size that is not a multiple of the chunk
    included; and a merge's memory stays within a small multiple of its result (a whole field's sorted float64
    copy was 5x it, the mapstore's high-water as its folded map grew)."""
    import tracemalloc

    from services.mapstore.core.fusion import SUM_COLUMNS

    rng = np.random.default_rng(1)
    k = 4 * SUM_COLUMNS + 3
    # as the frozen sums merge: a folded part of distinct voxels and the few keyframes folded since
    parts = _random_parts(rng, 1, k, rows=20000, voxel=0.02) + _random_parts(rng, 5, k, rows=1000, voxel=0.02)
    keys, (weight, xyz, codes, colours, count) = _sums_point_by_point(parts)
    tracemalloc.start()
    merged = merge_contributions(parts)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    np.testing.assert_array_equal(merged.keys, keys)
    np.testing.assert_allclose(merged.weight, weight, rtol=1e-12)
    np.testing.assert_allclose(merged.xyz, xyz, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(merged.codes, codes, rtol=1e-5, atol=1e-5)  # float32 sums of float64 additions
    np.testing.assert_allclose(merged.colours, colours, rtol=1e-5)
    np.testing.assert_array_equal(merged.count, count)
    result = sum(a.nbytes for a in (merged.keys, merged.weight, merged.xyz, merged.codes, merged.colours,
                                    merged.count))
    assert peak < 3 * result, (peak, result)  # 2.0x; 4.8x summed a whole field at once


@pytest.mark.parametrize("k_new, peak_limit", [(24, 2.0), (29, 4.0)])  # 3.3x and 5.7x re-summed whole
def test_a_grid_recoded_in_a_new_version_equals_its_parts_summed_in_it(k_new, peak_limit):
    """A new PCA basis re-sums the grid's codes from its contributions, each through its own version's map, a few
    columns and rows at a time (into the grid's own array where K is unchanged): equal to every row converted
    and added one by one, and within a small multiple of the grid's codes in memory."""
    import tracemalloc

    from services.common.pca_codes import CodeMap
    from services.mapstore.core.fusion import VoxelGrid

    rng = np.random.default_rng(2)
    k = 24
    parts = _random_parts(rng, 1, k, rows=20000, voxel=0.02) + _random_parts(rng, 8, k, rows=1000, voxel=0.02)
    grid = VoxelGrid(k)
    for p in parts:
        grid.apply(p, +1)
    cmap = CodeMap(rng.normal(size=(k_new, k)), rng.normal(size=k_new))
    cmaps = [cmap if i % 3 or k_new != k else None for i in range(len(parts))]  # some already in the new version
    tracemalloc.start()
    grid.recode([([p], c) for p, c in zip(parts, cmaps)], k_new)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    keys, (weight, _, codes, _, _) = _sums_point_by_point(parts, cmaps)
    fused = grid.fused()
    np.testing.assert_array_equal(fused.keys, keys)
    np.testing.assert_allclose(fused.codes, codes / weight[:, None], rtol=1e-4, atol=1e-5)
    codes_in_use = grid._codes[: len(grid)].nbytes  # the grid's arrays reserve many more slots (lazily backed)
    assert peak < peak_limit * codes_in_use, (peak / codes_in_use)


def test_a_grown_grid_never_copies_and_its_memory_follows_the_voxels_in_use():
    """Past its first slots a grid reserves address space for millions of voxels (lazily backed): growing further
    keeps the same arrays, the process's resident memory grows by about the slots written, not by the reservation,
    and the sums stay exact."""
    import psutil

    from services.mapstore.core.fusion import RESERVED_GRID_BYTES, VoxelGrid

    rng = np.random.default_rng(4)
    k, voxel = 32, 0.01
    parts = _random_parts(rng, 24, k, rows=6000, voxel=voxel)
    process = psutil.Process()
    before = process.memory_info().rss
    grid = VoxelGrid(k)
    grid.apply(parts[0], +1)  # past the first 4,096 slots: the reservation
    codes = grid._codes
    assert codes.nbytes > RESERVED_GRID_BYTES // 3
    for p in parts[1:]:
        grid.apply(p, +1)
    grown = process.memory_info().rss - before
    assert grid._codes is codes  # no copy
    written = len(grid) * (76 + 4 * k)
    assert grown < 2 * written + (16 << 20), (grown, written)  # not the ~1 GiB reserved
    keys, (weight, xyz, code_sums, _, count) = _sums_point_by_point(parts)
    fused = grid.fused()
    np.testing.assert_array_equal(fused.keys, keys)
    np.testing.assert_allclose(fused.codes, code_sums / weight[:, None], rtol=1e-4, atol=1e-5)
    np.testing.assert_array_equal(fused.count, count)


def test_a_grid_whose_voxels_empty_compacts_to_the_same_sums_and_gives_their_memory_back():
    """Voxels that empty at once (a person carved away) leave free slots; `compact` moves the voxels past the
    occupied count into them and hands the pages past it back: the fused map is the same to the bit, the process's
    resident memory falls by about the slots released, and the grid takes new voxels and removals after."""
    import psutil

    from services.mapstore.core.fusion import VoxelGrid

    rng = np.random.default_rng(5)
    k, voxel = 32, 0.01
    parts = _random_parts(rng, 24, k, rows=6000, voxel=voxel)
    grid = VoxelGrid(k)
    for p in parts:
        grid.apply(p, +1)
    assert grid.compact() == 0  # nothing free: nothing moved
    process = psutil.Process()
    for p in parts[::2]:  # half of them leave: their voxels empty all over the slots
        grid.apply(p, -1)
    kept = parts[1::2]
    expected = grid.fused()  # before the memory is read: its arrays are not the grid's
    before, free = process.memory_info().rss, len(grid._free)
    assert free > len(grid) // 2
    released = grid.compact()
    assert released == free and grid._used == len(grid) and not grid._free
    freed = before - process.memory_info().rss
    assert freed > 0.4 * released * (76 + 4 * k), (freed, released)  # 0.68 measured; ~0 without the release
    fused = grid.fused()
    for name in ("keys", "xyz", "codes", "colours", "weight", "count", "code_weight"):
        np.testing.assert_array_equal(getattr(fused, name), getattr(expected, name), err_msg=name)
    for p in parts[::2]:  # back in, then out again: the sums of the kept parts, point by point
        grid.apply(p, +1)
    for p in parts[::2]:
        grid.apply(p, -1)
    keys, (weight, xyz, code_sums, _, count) = _sums_point_by_point(kept)
    fused = grid.fused()
    np.testing.assert_array_equal(fused.keys, keys)
    np.testing.assert_allclose(fused.xyz, xyz / weight[:, None], rtol=1e-6)
    np.testing.assert_allclose(fused.codes, code_sums / weight[:, None], rtol=1e-4, atol=1e-5)
    np.testing.assert_array_equal(fused.count, count)
