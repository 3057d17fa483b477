"""A folding keyframe's voxels join the folded surface along their lines of sight (services/mapstore/core/snapping.py).

The function on hand-made voxel sums with a known wall; then the map core on the carving scene's wall seen with
depth noise, where revisits thicken the wall unless its voxels snap, and where the result must not depend on how
the keyframes were batched into folds (a restart folds them a page at a time).
"""
from __future__ import annotations

import numpy as np

from services.mapstore.config import FusionParams, MapParams
from services.mapstore.core.fusion import make_contribution, voxel_keys
from services.mapstore.core.map import KeyframeMap
from services.mapstore.core.snapping import contains, ray_offsets, snap_to_surface
from tests.helpers.carving_scene import WALL_Z, add_keyframe, cam_pose, label_codes, render
from tests.test_mapstore_memory import assert_same_fused

VOXEL = 0.1


def wall_keys(x: np.ndarray, y: np.ndarray, z: float) -> np.ndarray:
    """Sorted keys of the voxel layer holding the plane at depth z over the grid x × y."""
    gx, gy = np.meshgrid(x, y, indexing="ij")
    pts = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, z)], 1)
    return np.unique(voxel_keys(np.floor(pts / VOXEL).astype(np.int64)))


def test_loose_voxels_move_to_the_surface_along_the_ray_and_the_totals_are_kept():
    surface = wall_keys(np.arange(-1.0, 1.0, VOXEL / 2), np.arange(-1.0, 1.0, VOXEL / 2), 5.05)  # the layer z in [5, 5.1)
    centre = np.zeros(3)
    # points on rays from the origin through (x, y, 5.05), at depth offsets along the ray (in voxels), plus one ray
    # that misses the wall (x = 1.53: beside it)
    xs = np.array([0.03, 0.33, -0.43, 0.63, 0.52, 1.53])
    offsets = np.array([0.0, 0.9, -1.4, 1.8, 3.5, 0.0])
    directions = np.stack([xs, np.full(xs.size, 0.23), np.full(xs.size, 5.05)], 1)
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    on_wall = directions * (5.05 / directions[:, 2:3])
    points = on_wall + offsets[:, None] * VOXEL * directions
    rng = np.random.default_rng(0)
    c = make_contribution(points, rng.uniform(0.5, 1.0, xs.size), rng.normal(size=(xs.size, 4)).astype(np.float32),
                          rng.integers(0, 255, (xs.size, 3)), VOXEL)
    snapped = snap_to_surface(c, centre, surface, VOXEL, reach=2.0)

    own = voxel_keys(np.floor(points / VOXEL).astype(np.int64))
    where = {int(k): i for i, k in enumerate(snapped.keys)}
    assert contains(surface, own[:4]).tolist() == [True, False, False, False]
    landed = voxel_keys(np.floor(on_wall / VOXEL).astype(np.int64))
    assert all(int(landed[i]) in where for i in range(4))  # on the wall, or within 2 voxels of it along the ray
    assert not any(int(own[i]) in where for i in range(1, 4))  # ... and no longer where their points fell
    assert int(own[4]) in where and int(own[5]) in where  # 3.5 voxels off, and beside the wall: stay
    assert np.all(np.diff(snapped.keys) > 0)
    for name in ("weight", "xyz", "codes", "colours", "count"):
        np.testing.assert_allclose(getattr(snapped, name).sum(0), getattr(c, name).sum(0), rtol=1e-6)
    assert snap_to_surface(c, centre, surface, VOXEL, reach=0.0) is c
    assert snap_to_surface(c, centre, np.zeros(0, np.int64), VOXEL, reach=2.0) is c
    assert snap_to_surface(c, centre, surface, VOXEL, reach=0.4).keys.size == c.keys.size  # no step within reach
    np.testing.assert_allclose(ray_offsets(1.0), [-0.5, 0.5, -1.0, 1.0])


N = 70


def noisy_keyframe(i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(pose, disparity with 1.5 % noise (0.75 voxel of depth), codes) of keyframe i: a camera sliding back and forth along the wall, so
    later keyframes see what earlier ones saw."""
    pose = cam_pose(0.8 * np.sin(0.25 * i))
    disparity, _ = render(pose, [])
    noise = np.random.default_rng(100 + i).normal(scale=0.015, size=disparity.shape)
    return pose, (disparity * (1.0 + noise)).astype(np.float32), label_codes(np.zeros(disparity.shape, np.int64),
                                                                               seed=i)


def fold_noisy_wall(snap: float, fold_every: int) -> KeyframeMap:
    """The noisy wall's map with keyframes folded once 12 newer ones exist, ``fold_every`` keyframes at a time."""
    params = MapParams(fusion=FusionParams(voxel_size=VOXEL, voxel_mode="absolute", fold_snap_voxels=snap))
    m = KeyframeMap(params, voxel_size=VOXEL)
    for i in range(N):
        add_keyframe(m, i, *noisy_keyframe(i))
        m.refresh()
        if (i + 1) % fold_every == 0:
            m.fold(m.foldable(lambda k, newest=i: k < newest - 12))
    m.refresh()
    m.fold(m.foldable(lambda k: True))
    return m


def test_revisits_of_a_noisy_wall_fold_into_a_thin_wall_whatever_the_fold_batches():
    loose, thin = fold_noisy_wall(0.0, 1), fold_noisy_wall(2.0, 1)
    assert thin.folded_count == loose.folded_count > N - 20
    a, b = loose.fused(), thin.fused()
    thick = lambda f: np.abs(f.xyz[:, 2] - WALL_Z) > 1.5 * VOXEL  # noqa: E731  voxels off the wall's layers
    assert len(b.keys) < 0.8 * len(a.keys)
    assert thick(b).sum() < 0.6 * thick(a).sum()
    assert b.count.sum() == a.count.sum()  # every point is still in the map
    # the fused positions stay on the wall: the snapped map's mean distance no worse than the loose map's
    assert np.average(np.abs(b.xyz[:, 2] - WALL_Z), weights=b.weight) <= np.average(
        np.abs(a.xyz[:, 2] - WALL_Z), weights=a.weight) + 0.01 * VOXEL
    # folded in other batches (a restart folds a page at a time), the keyframes fold into the same map
    assert_same_fused(fold_noisy_wall(2.0, 7).fused(), b)
