"""The mapstore's end-of-stream export (map.ply, depth maps, the COLMAP model) at the size of a long stream.

A room orbit like the 10,000-frame memory check's (`bench/live.py --frames 10000`: 1203 keyframes, 312k map
points): cameras on a 3 m circle turning 23 times inside a 5 m cylinder wall, the map points on that wall, each
keyframe's depth grid ray-cast from the same wall, so every keyframe sees a part of the map as a real one does.
Prints the seconds of `export_all` and the observations the COLMAP model holds.

    python bench/export.py                      # 1203 keyframes, 312,000 points
    python bench/export.py --keyframes 300 --points 100000
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from services.mapstore.core.keyframe import KeyframeDepth
from services.mapstore.colmap import ColmapImage
from services.mapstore.export import export_all

WALL_RADIUS, CAMERA_RADIUS, WALL_HALF_HEIGHT, TURNS = 5.0, 3.0, 1.5, 23
GRID_H, GRID_W = 24, 32  # the 256x192 working size's 1/8 depth grid
INTRINSICS = np.array([200.0, 200.0, 127.5, 95.5])  # working-resolution pixels


def orbit_scene(keyframes: int, points: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    angle = rng.uniform(0, 2 * np.pi, points)
    xyz = np.stack([WALL_RADIUS * np.cos(angle), rng.uniform(-WALL_HALF_HEIGHT, WALL_HALF_HEIGHT, points),
                    WALL_RADIUS * np.sin(angle)], 1)
    rgb = rng.integers(0, 256, (points, 3), dtype=np.uint8)
    fx, fy, cx, cy = INTRINSICS / 8
    cx, cy = (INTRINSICS[2] + 0.5) / 8 - 0.5, (INTRINSICS[3] + 0.5) / 8 - 0.5
    rows, cols = np.mgrid[0:GRID_H, 0:GRID_W]
    depths, cameras = {}, {}
    for k in range(keyframes):
        theta = 2 * np.pi * TURNS * k / keyframes
        centre = np.array([CAMERA_RADIUS * np.cos(theta), 0.0, CAMERA_RADIUS * np.sin(theta)])
        z_axis = np.array([np.cos(theta), 0.0, np.sin(theta)])  # looking outwards, at the wall
        x_axis = np.cross([0.0, 1.0, 0.0], z_axis)
        world_from_cam = np.eye(4)
        world_from_cam[:3, :3] = np.stack([x_axis, np.cross(z_axis, x_axis), z_axis], 1)
        world_from_cam[:3, 3] = centre
        rays = np.stack([(cols - cx) / fx, (rows - cy) / fy, np.ones((GRID_H, GRID_W))], -1) @ world_from_cam[:3, :3].T
        # the ray's depth z (its camera z is 1) where it meets the wall: |centre + z ray| = R in x-z
        a = rays[..., 0] ** 2 + rays[..., 2] ** 2
        b = 2 * (centre[0] * rays[..., 0] + centre[2] * rays[..., 2])
        c = centre[0] ** 2 + centre[2] ** 2 - WALL_RADIUS ** 2
        z = (-b + np.sqrt(b * b - 4 * a * c)) / (2 * a)
        on_wall = np.abs(centre[1] + z * rays[..., 1]) <= WALL_HALF_HEIGHT
        depths[k] = KeyframeDepth(np.where(on_wall, 1.0 / z, 0.0).astype(np.float32), INTRINSICS)
        cameras[k] = ColmapImage(f"{k:06d}.jpg", world_from_cam, INTRINSICS, (GRID_W * 8, GRID_H * 8))
    return xyz, rgb, depths, cameras


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--keyframes", type=int, default=1203)
    parser.add_argument("--points", type=int, default=312_000)
    args = parser.parse_args()
    xyz, rgb, depths, cameras = orbit_scene(args.keyframes, args.points)
    with tempfile.TemporaryDirectory() as out:
        start = time.perf_counter()
        result = export_all(Path(out), xyz, rgb, depths, cameras, metric=False)
        seconds = time.perf_counter() - start
        lines = [x for x in (result.colmap / "images.txt").read_text().splitlines() if not x.startswith("#")]
        observations = sum(len(line.split()) // 3 for line in lines[1::2])
    print(f"export_all: {args.keyframes} keyframes, {args.points} points -> {seconds:.1f} s "
          f"({observations} COLMAP observations)")


if __name__ == "__main__":
    main()
