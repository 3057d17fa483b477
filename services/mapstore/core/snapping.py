"""A folding keyframe's voxels joined to the surface already folded along their lines of sight.

A wall seen on every lap of a long stream is measured again and again with the same depth noise, and each
measurement that lands a voxel in front of or behind the wall's voxels opens a new one: the map's surfaces
thicken and its voxel count grows with the stream, not with the scene (the 10,000-frame orbit: 47,649 voxels at
keyframe 128, 94,512 at keyframe 1,203, the voxels with three or more points growing as fast). Surfel and TSDF
fusion associate a new measurement with the surface already there along the camera's ray (ElasticFusion's
projective association, KinectFusion's truncation band); this does the same for the voxel sums: a voxel of a
folding keyframe that no folded voxel holds yet joins the nearest folded voxel within ``reach`` voxels along the
ray from the keyframe's camera through the voxel's mean point, and opens a new voxel only where no folded surface
is that near. Folding goes in keyframe order and a keyframe's contribution is final when it folds, so the result
depends on nothing but the keyframes (a restart folds them into the same map).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from services.mapstore.core.fusion import Contribution, sum_by_key, voxel_keys


def contains(sorted_keys: np.ndarray, keys: np.ndarray) -> np.ndarray:
    """(N,) bool: which of ``keys`` are in the ascending ``sorted_keys``."""
    if sorted_keys.size == 0:
        return np.zeros(keys.shape, bool)
    pos = np.searchsorted(sorted_keys, keys)
    return sorted_keys[np.minimum(pos, sorted_keys.size - 1)] == keys


def ray_offsets(reach: float, step: float = 0.5) -> np.ndarray:
    """Offsets along the ray in voxels, nearest first (in front before behind at equal distance): ±step, ±2·step,
    … up to ``reach``."""
    n = int(np.floor(reach / step + 1e-9))
    return np.array([s * k * step for k in range(1, n + 1) for s in (-1.0, 1.0)])


def snap_to_surface(c: Contribution, camera_centre: np.ndarray, surface_keys: np.ndarray, voxel_size: float,
                    reach: float) -> Contribution:
    """``c`` with each voxel that ``surface_keys`` lacks moved into the nearest voxel of ``surface_keys`` on the
    line of sight within ``reach`` voxels (its sums added to that voxel's); voxels with none that near stay.

    Args:
        c: a keyframe's contribution (distinct keys).
        camera_centre: (3,) the keyframe's camera centre in world coordinates.
        surface_keys: (S,) int64 ascending keys of the voxels already folded.
        voxel_size: voxel edge in world units.
        reach: how far along the ray (in voxels) a voxel may move; 0 returns ``c``.
    Returns:
        A contribution with distinct keys and the same totals (weight, points, sums).
    """
    if reach <= 0 or c.keys.size == 0 or surface_keys.size == 0:
        return c
    loose = np.flatnonzero(~contains(surface_keys, c.keys))
    if loose.size == 0:
        return c
    point = c.xyz[loose] / c.weight[loose, None]
    ray = point - np.asarray(camera_centre, np.float64)
    ray /= np.maximum(np.linalg.norm(ray, axis=1, keepdims=True), 1e-12)
    target = np.full(loose.size, -1, np.int64)
    open_ = np.ones(loose.size, bool)
    for t in ray_offsets(reach):
        probe = voxel_keys(np.floor((point + (t * voxel_size) * ray) / voxel_size).astype(np.int64))
        hit = open_ & contains(surface_keys, probe)
        target[hit] = probe[hit]
        open_ &= ~hit
    moved = loose[~open_]
    if moved.size == 0:
        return c
    keys = c.keys.copy()
    keys[moved] = target[~open_]
    return sum_by_key(dataclasses.replace(c, keys=keys))

