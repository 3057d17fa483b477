"""Map core: grid geometry, anchored points, consistency, incremental fusion vs brute force."""

from __future__ import annotations

import dataclasses
from collections import defaultdict

import numpy as np
import pytest

from services.mapstore.config import CarvingParams, ConsistencyParams, FusionParams, MapParams, PointParams
from services.mapstore.core.consistency import NeighbourView, depth_consistency
from services.mapstore.core.fusion import voxel_coords, voxel_keys
from services.mapstore.core.geometry import backproject_grid, grid_intrinsics, project, sample_cell_colours
from services.mapstore.core.keyframe import KeyframeContent, KeyframeDepth
from services.mapstore.core.map import KeyframeMap

H, W, K = 6, 8, 4
INTR = np.array([40.0, 42.0, 31.5, 23.5])  # working res 48x64


def pose(tx: float, yaw: float = 0.0) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    t = np.eye(4)
    t[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    t[0, 3] = tx
    return t


def make_keyframe(rng: np.random.Generator, kf_id: int) -> tuple[KeyframeContent, KeyframeDepth]:
    codes = rng.normal(size=(H, W, K)).astype(np.float16)
    colours = rng.integers(0, 256, size=(H, W, 3), dtype=np.uint8)
    disp = rng.uniform(0.2, 0.5, size=(H, W)).astype(np.float32)
    disp[0, 0] = 0.0  # unknown depth
    static = np.ones((H, W), np.float32)
    static[1, 1] = 0.1  # dynamic cell
    conf = rng.uniform(0.5, 1.0, size=(H, W)).astype(np.float32)
    content = KeyframeContent(kf_id, kf_id * 1000, codes, colours, (8 * H, 8 * W), 1)
    return content, KeyframeDepth(disp, INTR, static, conf)


def build_map(params: MapParams, n: int = 5, seed: int = 0) -> KeyframeMap:
    rng = np.random.default_rng(seed)
    m = KeyframeMap(params)
    for i in range(n):
        content, depth = make_keyframe(rng, i)
        m.add_content(content)
        m.set_depth(i, depth)
        m.set_pose(i, pose(0.1 * i, 0.02 * i))
    m.refresh()
    return m


def brute_force_fusion(m: KeyframeMap) -> dict[int, tuple]:
    """Per voxel key: (Σw, weighted mean xyz, weighted mean code, count), point by point."""
    acc: dict[int, list] = defaultdict(lambda: [0.0, np.zeros(3), np.zeros(K), 0])
    for kf_id in m.contents:
        pts = m.keyframe_points(kf_id)
        for x, w, z in zip(pts.xyz, pts.weight, pts.codes.astype(np.float64)):
            key = int(voxel_keys(np.floor(x / m.voxel_size).astype(np.int64)[None])[0])
            a = acc[key]
            a[0] += w
            a[1] += w * x
            a[2] += w * z
            a[3] += 1
    return {k: (a[0], a[1] / a[0], a[2] / a[0], a[3]) for k, a in acc.items()}


def test_grid_intrinsics_and_backprojection_hit_cell_centres():
    gk = grid_intrinsics(INTR)
    np.testing.assert_allclose(gk, [5.0, 5.25, 32.0 / 8 - 0.5, 24.0 / 8 - 0.5])
    disp = np.full((H, W), 0.25)
    pts = backproject_grid(disp, gk).reshape(-1, 3)
    proj = project(pts, INTR)  # into the working-res image: cell (r, c) centre is (8c + 3.5, 8r + 3.5)
    rows, cols = np.divmod(np.arange(H * W), W)
    np.testing.assert_allclose(proj.u, 8 * cols + 3.5, atol=1e-9)
    np.testing.assert_allclose(proj.v, 8 * rows + 3.5, atol=1e-9)
    np.testing.assert_allclose(proj.z, 4.0)


def test_cell_colours_are_bilinear_samples_at_cell_centres():
    img = np.random.default_rng(1).integers(0, 256, size=(8 * H, 8 * W, 3), dtype=np.uint8)
    out = sample_cell_colours(img)
    r, c = 2, 5
    x, y = 8 * c + 3.5, 8 * r + 3.5  # bilinear weights 0.5/0.5 on pixels floor and ceil
    x0, y0 = int(np.floor(x)), int(np.floor(y))
    ref = img[y0 : y0 + 2, x0 : x0 + 2].reshape(-1, 3).astype(float).mean(0)
    np.testing.assert_array_equal(out[r, c], np.rint(ref).astype(np.uint8))
    assert out.shape == (H, W, 3)


def test_voxel_keys_round_trip():
    ijk = np.random.default_rng(2).integers(-(2**20), 2**20, size=(100, 3))
    np.testing.assert_array_equal(voxel_coords(voxel_keys(ijk)), ijk)


def test_unknown_dynamic_and_low_weight_cells_are_left_out():
    params = MapParams(points=PointParams(min_weight=0.6), consistency=ConsistencyParams(neighbours=0))
    m = build_map(params, n=1)
    pts = m.keyframe_points(0)
    depth = m.depths[0]
    assert 0 not in pts.cells  # disparity 0
    assert 1 * W + 1 not in pts.cells  # static weight 0.1 → dynamic
    expected = np.flatnonzero((depth.confidence.reshape(-1) >= 0.6) & (depth.disparity.reshape(-1) > 0)
                              & (depth.static_weight.reshape(-1) >= 0.5))
    np.testing.assert_array_equal(np.sort(pts.cells), expected)


def test_depth_consistency_agrees_occludes_and_violates():
    params = ConsistencyParams(rel_tolerance=0.05, unverified=0.7)
    disp = np.full((H, W), 0.25, np.float32)  # neighbour sees a wall at z = 4
    view = NeighbourView(np.eye(4), disp, INTR)
    gk = grid_intrinsics(INTR)
    rays = backproject_grid(np.ones((H, W)), gk).reshape(-1, 3)[:3]  # three rays at z = 1
    pts = np.concatenate([rays * 4.0, rays * 6.0, rays * 2.0])  # on, behind (occluded), in front
    out = depth_consistency(pts, [view], params)
    np.testing.assert_allclose(out, [1, 1, 1, 0.7, 0.7, 0.7, 0, 0, 0])


def test_relative_voxel_size_is_fraction_of_median_depth():
    m = build_map(MapParams(fusion=FusionParams(voxel_size=0.1, voxel_mode="relative")), n=1)
    z = 1.0 / m.depths[0].disparity[m.depths[0].disparity > 0]
    static_ok = m.depths[0].static_weight[m.depths[0].disparity > 0] >= 0.5
    assert m.voxel_size == pytest.approx(0.1 * np.median(z[static_ok]))


@pytest.mark.parametrize("neighbours", [0, 2])
def test_pose_correction_moves_exactly_that_keyframes_points(neighbours):
    # neighbours 0 also switches carving off: with no check across keyframes, a keyframe is fused in isolation
    params = MapParams(consistency=ConsistencyParams(neighbours=neighbours, rel_tolerance=0.5),
                       carving=CarvingParams(later_keyframes=16 if neighbours else 0),
                       fusion=FusionParams(voxel_size=0.05))
    m = build_map(params)
    before = {i: m.keyframe_points(i) for i in m.contents}
    fused_before = m.fused()
    new_pose = pose(0.3, 0.5) @ m.poses[2]
    m.set_pose(2, new_pose)
    m.refresh()
    for i in m.contents:
        after = m.keyframe_points(i)
        if i != 2:
            common, ia, ib = np.intersect1d(before[i].cells, after.cells, return_indices=True)
            np.testing.assert_array_equal(before[i].xyz[ia], after.xyz[ib])  # bit-identical
    moved = m.keyframe_points(2)
    # the cells both poses keep (which later views carve depends on where the keyframe's points are)
    _, ia, ib = np.intersect1d(before[2].cells, moved.cells, return_indices=True)
    assert len(ia) > 0.8 * len(moved.cells)
    cam = np.linalg.inv(m.poses[2]) @ np.c_[moved.xyz[ib], np.ones(len(ib))].T
    old_cam = np.linalg.inv(pose(0.2, 0.04)) @ np.c_[before[2].xyz[ia], np.ones(len(ia))].T
    np.testing.assert_allclose(cam[:3], old_cam[:3], atol=1e-9)  # same camera-frame points
    assert not np.allclose(moved.xyz[ib], before[2].xyz[ia])
    if neighbours == 0:  # fused voxels change only where keyframe 2's old or new points fall
        fused_after = m.fused()
        touched = set(voxel_keys(np.floor(before[2].xyz / m.voxel_size).astype(np.int64)).tolist())
        touched |= set(voxel_keys(np.floor(moved.xyz / m.voxel_size).astype(np.int64)).tolist())
        a = dict(zip(fused_before.keys.tolist(), fused_before.xyz))
        b = dict(zip(fused_after.keys.tolist(), fused_after.xyz))
        for key in (set(a) | set(b)) - touched:
            np.testing.assert_allclose(a[key], b[key], rtol=1e-12)


def test_incremental_fusion_equals_brute_force_after_updates():
    params = MapParams(consistency=ConsistencyParams(neighbours=1, rel_tolerance=0.3),
                       fusion=FusionParams(voxel_size=0.3, voxel_mode="absolute"))
    m = build_map(params, n=6, seed=3)
    rng = np.random.default_rng(4)
    m.set_pose(1, pose(0.5, 0.3))
    _, depth = make_keyframe(rng, 3)
    m.set_depth(3, depth)
    m.remove(5)
    m.refresh()
    fused = m.fused()
    ref = brute_force_fusion(m)
    assert set(fused.keys.tolist()) == set(ref)
    for i, key in enumerate(fused.keys.tolist()):
        w, x, z, n = ref[key]
        assert fused.count[i] == n
        np.testing.assert_allclose(fused.weight[i], w, rtol=1e-9)
        np.testing.assert_allclose(fused.xyz[i], x, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(fused.codes[i], z, rtol=1e-4, atol=1e-4)


def test_maps_and_poses_resent_unchanged_refuse_nothing_and_one_changed_value_refuses_its_keyframe():
    """ba's final graph resends every held keyframe's maps and pose; only those its BA moved are fused again."""
    m = build_map(MapParams(fusion=FusionParams(voxel_size=0.3, voxel_mode="absolute")), n=5, seed=6)
    copies = {k: KeyframeDepth(d.disparity.copy(), d.intrinsics.copy(), d.static_weight.copy(), d.confidence.copy())
              for k, d in m.depths.items()}  # equal values in new arrays, as a decoded message carries them
    for k, depth in copies.items():
        m.set_depth(k, depth)
        m.set_pose(k, m.poses[k].copy())
    assert m.refresh().refreshed == []
    for field in ("disparity", "intrinsics", "static_weight", "confidence"):
        changed = getattr(copies[3], field).copy()
        changed.flat[-1] *= 1.01
        m.set_depth(3, dataclasses.replace(copies[3], **{field: changed}))
        assert 3 in m.refresh().refreshed, field
        m.set_depth(3, copies[3])
        m.refresh()


def test_rebuild_equals_incremental():
    params = MapParams(fusion=FusionParams(voxel_size=0.3, voxel_mode="absolute"))
    m = build_map(params, n=4, seed=5)
    m.set_pose(0, pose(-0.2, 0.1))
    m.refresh()
    inc = m.fused()
    full = m.rebuild().voxels
    assert full == len(inc.keys)
    np.testing.assert_allclose(m.fused().xyz, inc.xyz, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(m.fused().codes, inc.codes, rtol=1e-4, atol=1e-5)


def test_far_cells_are_left_out_relative_to_the_median_depth():
    from services.mapstore.config import PointParams
    from services.mapstore.core.keyframe import KeyframeDepth, candidate_points

    disparity = np.full((6, 8), 0.5, np.float32)  # 2 m
    disparity[0, :3] = 1e-5  # 100 km: the sky of a monocular estimate
    k = np.array([100.0, 100.0, 31.5, 23.5])
    points = candidate_points(KeyframeDepth(disparity, k), PointParams(max_depth_ratio=20.0))
    assert len(points.cells) == 6 * 8 - 3 and not set(points.cells) & {0, 1, 2}
    assert np.all(points.points_cam[:, 2] < 2.1)
