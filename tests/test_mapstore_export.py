"""Exports read back: PLY (binary and ascii), depth maps (PNG mm / npz), COLMAP text round trip."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from services.mapstore.core.keyframe import KeyframeDepth
from services.mapstore.export import (ColmapImage, export_all, label_palette, quaternion_wxyz, read_colmap, read_ply,
                                      rotation_from_wxyz, write_depth_maps, write_ply)


def random_pose(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    t = np.eye(4)
    t[:3, :3] = rotation_from_wxyz(q)
    t[:3, 3] = rng.normal(size=3) * 3
    return t


@pytest.mark.parametrize("binary", [True, False])
@pytest.mark.parametrize("labels", [True, False])
def test_ply_round_trip(tmp_path, binary, labels):
    rng = np.random.default_rng(0)
    xyz = rng.normal(size=(50, 3)).astype(np.float32)
    rgb = rng.integers(0, 256, (50, 3), dtype=np.uint8)
    lab = label_palette(5)[rng.integers(0, 5, 50)] if labels else None
    path = write_ply(tmp_path / "map.ply", xyz, rgb, lab, binary=binary)
    header = path.read_bytes().split(b"end_header\n")[0].decode()
    assert ("binary_little_endian" in header) == binary and "element vertex 50" in header
    rec = read_ply(path)
    np.testing.assert_allclose(np.stack([rec["x"], rec["y"], rec["z"]], 1), xyz, rtol=1e-6)
    np.testing.assert_array_equal(np.stack([rec["red"], rec["green"], rec["blue"]], 1), rgb)
    assert ("label_red" in rec.dtype.names) == labels
    if labels:
        np.testing.assert_array_equal(np.stack([rec["label_red"], rec["label_green"], rec["label_blue"]], 1), lab)


def test_label_palette_colours_are_distinct():
    pal = label_palette(12)
    assert pal.shape == (12, 3) and len({tuple(c) for c in pal.tolist()}) == 12


def test_quaternion_round_trip_and_known_answer():
    rng = np.random.default_rng(1)
    for _ in range(50):
        r = random_pose(rng)[:3, :3]
        q = quaternion_wxyz(r)
        assert q[0] >= 0 and np.isclose(np.linalg.norm(q), 1)
        np.testing.assert_allclose(rotation_from_wxyz(q), r, atol=1e-12)
    rz90 = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]])  # 90° about z: q = (cos 45°, 0, 0, sin 45°)
    np.testing.assert_allclose(quaternion_wxyz(rz90), [np.sqrt(0.5), 0, 0, np.sqrt(0.5)], atol=1e-12)


def test_depth_maps_png_mm_and_npz(tmp_path):
    disp = np.array([[0.5, 0.0], [2.0, 1 / 70.0]], np.float32)  # 2 m, unknown, 0.5 m, 70 m (clipped)
    depths = {3: KeyframeDepth(disp, np.array([10.0, 10, 7.5, 7.5]))}
    (png,) = write_depth_maps(tmp_path / "m", depths, metric=True)
    mm = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
    assert mm.dtype == np.uint16 and mm.shape == (16, 16)
    np.testing.assert_array_equal(mm[::8, ::8], [[2000, 0], [500, 65535]])
    assert np.all(mm[:8, :8] == 2000)  # nearest upsampling of the grid cell
    (npz,) = write_depth_maps(tmp_path / "s", depths, metric=False)
    z = np.load(npz)["depth"]
    np.testing.assert_allclose(z[::8, ::8], [[2.0, 0.0], [0.5, 70.0]], rtol=1e-6)


def test_colmap_round_trip_matches_poses_and_intrinsics(tmp_path):
    rng = np.random.default_rng(2)
    cams = {i: ColmapImage(f"{i:06d}.jpg", random_pose(rng), np.array([500.0, 505, 255.5 + i, 191.5]), (512, 384))
            for i in (0, 4, 9)}
    write_colmap_dir = tmp_path / "colmap"
    from services.mapstore.export import write_colmap

    write_colmap(write_colmap_dir, cams)
    back = read_colmap(write_colmap_dir)
    assert set(back) == {c.name for c in cams.values()}
    for cam in cams.values():
        got = back[cam.name]
        np.testing.assert_allclose(got.world_from_cam, cam.world_from_cam, atol=1e-12)
        np.testing.assert_allclose(got.intrinsics, cam.intrinsics)
        assert got.size == (512, 384)
    line = (write_colmap_dir / "cameras.txt").read_text().splitlines()[2]
    assert line.split()[:4] == ["1", "PINHOLE", "512", "384"] and float(line.split()[6]) == 256.0  # cx + 0.5
    # images.txt holds cam_from_world: projecting a world point with it gives camera coordinates
    img_line = (write_colmap_dir / "images.txt").read_text().splitlines()[3].split()
    r, t = rotation_from_wxyz(np.array(img_line[1:5], float)), np.array(img_line[5:8], float)
    p_world = rng.normal(size=3)
    p_cam = np.linalg.inv(cams[0].world_from_cam) @ np.r_[p_world, 1]
    np.testing.assert_allclose(r @ p_world + t, p_cam[:3], atol=1e-12)


def test_export_all_writes_every_artifact(tmp_path):
    rng = np.random.default_rng(3)
    depths = {1: KeyframeDepth(np.full((2, 3), 0.5, np.float32), np.array([10.0, 10, 11.5, 7.5]))}
    cams = {1: ColmapImage("000001.jpg", random_pose(rng), depths[1].intrinsics, (24, 16))}
    res = export_all(tmp_path, rng.normal(size=(4, 3)), np.zeros((4, 3), np.uint8), depths, cams, metric=False,
                     jpegs={1: b"jpegbytes"})
    assert len(read_ply(res.ply)) == 4
    assert [p.name for p in res.depth_maps] == ["000001.npz"]
    assert (res.colmap / "points3D.txt").exists() and set(read_colmap(res.colmap)) == {"000001.jpg"}
    assert res.images[0].read_bytes() == b"jpegbytes"
