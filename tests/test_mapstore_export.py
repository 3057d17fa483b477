"""Exports read back: PLY (binary and ascii), depth maps (PNG mm / npz), COLMAP text round trip and which points a
keyframe sees (COLMAP's own reading of the model: tests/test_colmap_export.py)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from scipy.spatial.transform import Rotation

from services.mapstore.core.keyframe import KeyframeDepth
from services.mapstore.colmap import ColmapImage, read_colmap, visible_points, write_colmap
from services.mapstore.export import (export_all, label_palette, read_depth_map, read_ply, write_depth_maps,
                                      write_ply)


def random_pose(rng: np.random.Generator) -> np.ndarray:
    t = np.eye(4)
    t[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    t[:3, 3] = rng.normal(size=3) * 3
    return t


def data_lines(path) -> list[str]:
    return [line for line in path.read_text().splitlines() if not line.startswith("#")]


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
    # read back as depth either way (the PNG's 70 m clipped at 65.535 m)
    np.testing.assert_allclose(read_depth_map(npz)[::8, ::8], [[2.0, 0.0], [0.5, 70.0]], rtol=1e-6)
    np.testing.assert_allclose(read_depth_map(png)[::8, ::8], [[2.0, 0.0], [0.5, 65.535]])
    # written again once the map became metric (an earlier export, or the keyframe's fold): one file, the new kind
    write_depth_maps(tmp_path / "s", depths, metric=True)
    assert [p.name for p in (tmp_path / "s").iterdir()] == ["000003.png"]


def test_colmap_round_trip_matches_poses_and_intrinsics(tmp_path):
    rng = np.random.default_rng(2)
    k = np.array([500.0, 505, 255.5, 191.5])
    cams = {i: ColmapImage(f"{i:06d}.jpg", random_pose(rng), k, (512, 384)) for i in (0, 4, 9)}
    folder = write_colmap(tmp_path / "colmap", cams)
    back = read_colmap(folder)
    assert set(back) == {c.name for c in cams.values()}
    for cam in cams.values():
        got = back[cam.name]
        np.testing.assert_allclose(got.world_from_cam, cam.world_from_cam, atol=1e-12)
        np.testing.assert_allclose(got.intrinsics, cam.intrinsics)
        assert got.size == (512, 384)
    (line,) = data_lines(folder / "cameras.txt")  # one camera shared by every image
    assert line.split()[:4] == ["1", "PINHOLE", "512", "384"] and float(line.split()[6]) == 256.0  # cx + 0.5
    # images.txt holds cam_from_world as (qw, qx, qy, qz, t): projecting a world point with it gives camera
    # coordinates
    img_line = data_lines(folder / "images.txt")[0].split()
    qw, qx, qy, qz = map(float, img_line[1:5])
    r, t = Rotation.from_quat([qx, qy, qz, qw]).as_matrix(), np.array(img_line[5:8], float)
    assert qw >= 0 and img_line[8:] == ["1", "000000.jpg"]
    p_world = rng.normal(size=3)
    p_cam = np.linalg.inv(cams[0].world_from_cam) @ np.r_[p_world, 1]
    np.testing.assert_allclose(r @ p_world + t, p_cam[:3], atol=1e-12)
    assert data_lines(folder / "points3D.txt") == []  # no map points given


def test_an_image_that_cannot_share_the_camera_is_left_out(tmp_path, caplog):
    rng = np.random.default_rng(4)
    k = np.array([500.0, 505, 255.5, 191.5])
    cams = {0: ColmapImage("0.jpg", random_pose(rng), k, (512, 384)), 1: ColmapImage("1.jpg", random_pose(rng), k,
                                                                                       (256, 192))}
    assert set(read_colmap(write_colmap(tmp_path, cams))) == {"0.jpg"}
    assert "another size" in caplog.text


def test_a_keyframe_sees_the_points_on_its_depth_and_no_others():
    """A wall at 2 m fills a 4x3-cell view (32x24 px, fx = fy = 20); points on it (or 4.5 % behind it: within the
    5 % tolerance; or at the last pixel) are seen, points 10 % behind (occluded) or in front (not there in this
    view), outside the image, behind the camera or on a cell of unknown depth are not."""
    disparity = np.full((3, 4), 0.5, np.float32)
    disparity[0, 0] = 0.0  # unknown
    depth = KeyframeDepth(disparity, np.array([20.0, 20.0, 15.5, 11.5]))

    def at(u, v, z):  # the world point of pixel (u, v) at depth z; the camera is the world frame
        return [(u - 15.5) / 20.0 * z, (v - 11.5) / 20.0 * z, z]

    points = np.array([at(20, 12, 2.0), at(20, 12, 2.2), at(20, 12, 1.8), at(20, 12, 2.09), at(40, 12, 2.0),
                       [0.0, 0.0, -2.0], at(3, 3, 2.0), at(31, 23, 2.0)])
    seen = visible_points(points, np.eye(4), depth, rel_tolerance=0.05)
    np.testing.assert_array_equal(seen, [0, 3, 7])


def test_export_all_writes_every_artifact(tmp_path):
    rng = np.random.default_rng(3)
    depths = {1: KeyframeDepth(np.full((2, 3), 0.5, np.float32), np.array([10.0, 10, 11.5, 7.5]))}
    cams = {1: ColmapImage("000001.jpg", random_pose(rng), depths[1].intrinsics, (24, 16))}
    res = export_all(tmp_path, rng.normal(size=(4, 3)), np.zeros((4, 3), np.uint8), depths, cams, metric=False,
                     jpegs={1: b"jpegbytes"})
    assert len(read_ply(res.ply)) == 4
    assert [p.name for p in res.depth_maps] == ["000001.npz"]
    assert {p.name for p in res.colmap.iterdir()} == {f"{name}.{ext}" for name in ("cameras", "images", "points3D")
                                                      for ext in ("txt", "bin")}
    assert set(read_colmap(res.colmap)) == {"000001.jpg"}
    assert res.images[0].read_bytes() == b"jpegbytes"
