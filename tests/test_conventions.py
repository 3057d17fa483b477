"""Each rule of docs/CONVENTIONS.md as an assert, checked across the modules that must agree on it."""
from __future__ import annotations

import cv2
import numpy as np
import torch

from services.evaluation.trajectory_io import Trajectory, read_tum, write_tum
from services.features.core.depth import sensor_disparity
from services.features.core.geometry import Intrinsics
from services.ingest.sources import open_source
from services.mapstore.core.geometry import grid_intrinsics
from services.mapstore.colmap import ColmapImage, write_colmap
from services.synth import SynthConfig, SynthWorld

K = Intrinsics(500.0, 480.0, 255.5, 191.5)


def test_resize_rule_keeps_pixel_centres():
    """fx' = s·fx, cx' = s·(cx + 0.5) − 0.5: the image edge −0.5 maps to −0.5 and the centre to the centre."""
    s = 0.25
    k = K.scaled(s, s)
    assert np.isclose(k.fx, s * K.fx) and np.isclose(k.cx, s * (K.cx + 0.5) - 0.5)
    assert np.isclose((-0.5 + 0.5) * s - 0.5, -0.5)


def test_features_and_mapstore_agree_on_the_grid():
    """Cell (r, c) is centred on pixel (8c + 3.5, 8r + 3.5); both services derive the same grid intrinsics."""
    ours = np.array(K.to_grid())
    theirs = grid_intrinsics(np.array(K))
    np.testing.assert_allclose(ours, theirs)
    # a ray through pixel (8c+3.5, 8r+3.5) hits grid coordinate (c, r)
    c, r = 5, 7
    x = (8 * c + 3.5 - K.cx) / K.fx
    assert np.isclose(ours[0] * x + ours[2], c)
    y = (8 * r + 3.5 - K.cy) / K.fy
    assert np.isclose(ours[1] * y + ours[3], r)


def test_ba_projection_uses_the_same_pinhole():
    from services.ba.core.projective import project

    point = torch.tensor([[0.3, -0.2, 2.0]], dtype=torch.float64)
    uv = project(point, torch.tensor(np.array(K)))
    np.testing.assert_allclose(uv.numpy()[0], [K.fx * 0.15 + K.cx, K.fy * -0.1 + K.cy])


def test_poses_are_world_from_cam_and_depth_is_camera_z():
    world = SynthWorld(SynthConfig(n_frames=2, width=64, height=48))
    frame = world.render(0)
    fx, fy, cx, cy = frame.intrinsics
    v, u = 30, 20
    z = frame.depth[v, u]
    cam = np.array([(u - cx) / fx * z, (v - cy) / fy * z, z, 1.0])
    world_point = frame.world_from_cam @ cam
    back = np.linalg.inv(frame.world_from_cam) @ world_point
    assert z > 0 and np.isclose(back[2], z)  # z forward
    # y down: a point below the optical axis in the image is lower in the z-up world
    lower = frame.world_from_cam @ np.array([0.0, 1.0, 2.0, 1.0])
    upper = frame.world_from_cam @ np.array([0.0, -1.0, 2.0, 1.0])
    assert lower[2] < upper[2]


def test_disparity_is_inverse_depth():
    disparity = sensor_disparity(np.full((48, 64), 2.0, np.float32), (48, 64))
    np.testing.assert_allclose(disparity, 0.5)
    assert disparity.shape == (6, 8)


def test_tum_files_hold_xyzw_quaternions_camera_to_world(tmp_path):
    pose = np.eye(4)
    pose[:3, :3] = cv2.Rodrigues(np.array([0.0, 0.0, np.pi / 2]))[0]  # 90° about z
    pose[:3, 3] = [1, 2, 3]
    write_tum(tmp_path / "t.txt", Trajectory(np.array([1.5]), pose[None]))
    fields = [float(x) for x in (tmp_path / "t.txt").read_text().split("\n")[-2].split()]
    np.testing.assert_allclose(fields[1:4], [1, 2, 3])
    np.testing.assert_allclose(np.abs(fields[4:]), [0, 0, np.sqrt(0.5), np.sqrt(0.5)], atol=1e-9)
    np.testing.assert_allclose(read_tum(tmp_path / "t.txt").world_from_cam[0], pose, atol=1e-9)


def test_tum_and_colmap_files_hold_the_same_quaternion_in_their_orders(tmp_path):
    """TUM: world_from_cam as (x, y, z, w); COLMAP: cam_from_world as (w, x, y, z); both with w >= 0."""
    pose = np.eye(4)
    pose[:3, :3] = cv2.Rodrigues(np.array([0.3, -2.5, 0.4]))[0]  # over 90°: a sign to choose
    write_tum(tmp_path / "t.txt", Trajectory(np.array([0.0]), pose[None]))
    tum = np.array((tmp_path / "t.txt").read_text().splitlines()[-1].split()[4:], float)
    cam = ColmapImage("0.jpg", np.linalg.inv(pose), np.array(K), (512, 384))  # its cam_from_world is `pose`
    folder = write_colmap(tmp_path / "colmap", {0: cam})
    line = next(x for x in (folder / "images.txt").read_text().splitlines() if not x.startswith("#"))
    colmap = np.array(line.split()[1:5], float)
    assert tum[3] >= 0 and colmap[0] >= 0
    np.testing.assert_allclose(colmap, np.roll(tum, 1), atol=1e-9)


def test_wire_images_are_rgb(tmp_path):
    red = np.zeros((8, 8, 3), np.uint8)
    red[..., 2] = 255  # OpenCV writes BGR: this file is pure red
    cv2.imwrite(str(tmp_path / "0.png"), red)
    frame = next(iter(open_source(str(tmp_path)).frames()))
    assert frame.rgb[0, 0].tolist() == [255, 0, 0]
