"""The COLMAP model of an export, read back by COLMAP itself (pycolmap) on the synthetic world, whose poses,
intrinsics and depth are exact: one shared camera, every keyframe as an image, points with tracks that land
where the ground truth says the points are, and the text and binary models agree."""
from __future__ import annotations

import numpy as np
import pycolmap
import pytest

from services.mapstore.core.keyframe import KeyframeDepth
from services.mapstore import colmap
from services.mapstore.colmap import ColmapImage, ColmapParams, ColmapWriter, read_colmap, visible_points
from services.mapstore.export import export_all
from services.synth import SynthConfig, SynthWorld

KEYFRAMES = (0, 4, 8, 12, 16, 20)
POINTS_PER_FRAME = 400
WIDTH, HEIGHT = 256, 192


def grid_disparity(depth: np.ndarray) -> np.ndarray:
    """(H/8, W/8) disparity at each cell's centre: the mean of 1/z over its 2x2 central pixels (exact on planes,
    where 1/z is affine in the pixel coordinates)."""
    inv = 1.0 / depth.astype(np.float64)
    return ((inv[3::8, 3::8] + inv[3::8, 4::8] + inv[4::8, 3::8] + inv[4::8, 4::8]) / 4).astype(np.float32)


@pytest.fixture(scope="module")
def scene():
    """Six keyframes of the synthetic room (a person walks through: a moving object) and a map of exact surface
    points, some from each keyframe's depth."""
    world = SynthWorld(SynthConfig(width=WIDTH, height=HEIGHT, n_frames=40, texels_per_metre=32.0))
    rng = np.random.default_rng(0)
    frames = {k: world.render(k) for k in KEYFRAMES}
    xyz = []
    for f in frames.values():
        v, u = rng.integers(0, HEIGHT, POINTS_PER_FRAME), rng.integers(0, WIDTH, POINTS_PER_FRAME)
        fx, fy, cx, cy = f.intrinsics
        z = f.depth[v, u].astype(np.float64)
        cam = np.stack([(u - cx) / fx * z, (v - cy) / fy * z, z, np.ones_like(z)], 1)
        xyz.append((cam @ f.world_from_cam.T)[:, :3])
    xyz = np.concatenate(xyz)
    rgb = rng.integers(0, 256, (len(xyz), 3), dtype=np.uint8)
    depths = {k: KeyframeDepth(grid_disparity(f.depth), f.intrinsics) for k, f in frames.items()}
    cameras = {k: ColmapImage(f"{k:06d}.jpg", f.world_from_cam, f.intrinsics, (WIDTH, HEIGHT))
               for k, f in frames.items()}
    return frames, xyz, rgb, depths, cameras


def export(tmp_path, scene, params: ColmapParams | None = None):
    frames, xyz, rgb, depths, cameras = scene
    res = export_all(tmp_path, xyz, rgb, depths, cameras, metric=True, colmap=params)
    return res.colmap


def test_colmap_reads_one_camera_every_keyframe_and_tracked_points(tmp_path, scene):
    frames, xyz, rgb, _, _ = scene
    rec = pycolmap.Reconstruction(export(tmp_path, scene))
    assert rec.num_cameras() == 1
    cam = rec.cameras[1]
    fx, fy, cx, cy = frames[0].intrinsics
    assert cam.model == pycolmap.CameraModelId.PINHOLE and (cam.width, cam.height) == (WIDTH, HEIGHT)
    np.testing.assert_allclose(cam.params, [fx, fy, cx + 0.5, cy + 0.5])  # COLMAP's pixel centres at +0.5
    by_name = {im.name: im for im in rec.images.values()}
    assert set(by_name) == {f"{k:06d}.jpg" for k in KEYFRAMES}
    for k, f in frames.items():
        im = by_name[f"{k:06d}.jpg"]
        assert im.camera_id == 1
        np.testing.assert_allclose(im.cam_from_world().matrix(), np.linalg.inv(f.world_from_cam)[:3], atol=1e-12)
    assert rec.num_points3D() > len(xyz) // 2  # the keyframes overlap: most points are seen twice or more
    for pid, point in rec.points3D.items():
        elements = point.track.elements
        assert len(elements) >= 2
        np.testing.assert_array_equal(point.xyz, xyz[pid - 1])  # POINT3D_ID = map.ply row + 1
        np.testing.assert_array_equal(point.color, rgb[pid - 1])
        for el in elements:
            assert rec.images[el.image_id].points2D[el.point2D_idx].point3D_id == pid


def test_observations_reproject_and_agree_with_the_ground_truth(tmp_path, scene):
    frames = scene[0]
    rec = pycolmap.Reconstruction(export(tmp_path, scene))
    errors, agree, total = [], 0, 0
    for pid, point in rec.points3D.items():
        for el in point.track.elements:
            im = rec.images[el.image_id]
            xy = im.points2D[el.point2D_idx].xy
            p_cam = im.cam_from_world() * point.xyz
            errors.append(np.linalg.norm(rec.cameras[1].img_from_cam(p_cam) - xy))
            # ground truth: the rendered depth at that pixel (ours: centres at integers) is the point's depth
            f = frames[int(im.name[:6])]
            u, v = int(np.floor(xy[0])), int(np.floor(xy[1]))
            total += 1
            agree += abs(f.depth[v, u] - p_cam[2]) <= 0.02 * f.depth[v, u]
    assert max(errors) < 1e-6
    # the export decides visibility on the 8x8 depth grid with a 5 % tolerance; at the pixel, a few observations
    # at depth edges see the surface next to the point, and a few on the walking person its new place
    assert agree / total > 0.95, (agree, total)  # measured: 97.3 % of 9798


def test_points_the_ground_truth_shows_in_two_keyframes_are_tracked(tmp_path, scene):
    frames, xyz = scene[0], scene[1]
    rec = pycolmap.Reconstruction(export(tmp_path, scene))
    seen_by = np.zeros(len(xyz), int)
    for f in frames.values():
        p = np.c_[xyz, np.ones(len(xyz))] @ np.linalg.inv(f.world_from_cam).T
        fx, fy, cx, cy = f.intrinsics
        u, v = np.rint(p[:, 0] / p[:, 2] * fx + cx), np.rint(p[:, 1] / p[:, 2] * fy + cy)
        inside = (p[:, 2] > 0) & (u >= 0) & (u < WIDTH) & (v >= 0) & (v < HEIGHT)
        z = np.full(len(xyz), np.nan)
        z[inside] = f.depth[v[inside].astype(int), u[inside].astype(int)]
        seen_by += inside & (np.abs(z - p[:, 2]) <= 0.01 * z)
    truly_tracked = set(np.flatnonzero(seen_by >= 2) + 1)
    exported = set(rec.points3D)
    assert len(truly_tracked & exported) / len(truly_tracked) > 0.9  # measured: 97.6 % of 2250


def test_text_and_binary_models_agree(tmp_path, scene):
    folder = export(tmp_path, scene)
    text, binary = pycolmap.Reconstruction(), pycolmap.Reconstruction()
    text.read_text(folder)
    binary.read_binary(folder)
    assert text.cameras[1].params.tolist() == binary.cameras[1].params.tolist()
    assert set(text.images) == set(binary.images) and set(text.points3D) == set(binary.points3D)
    for i, im in text.images.items():
        other = binary.images[i]
        assert im.name == other.name
        np.testing.assert_array_equal(im.cam_from_world().matrix(), other.cam_from_world().matrix())
        assert [(p.xy.tolist(), p.point3D_id) for p in im.points2D] == \
               [(p.xy.tolist(), p.point3D_id) for p in other.points2D]
    for pid, point in text.points3D.items():
        other = binary.points3D[pid]
        assert point.xyz.tolist() == other.xyz.tolist() and point.color.tolist() == other.color.tolist()
        assert [(e.image_id, e.point2D_idx) for e in point.track.elements] == \
               [(e.image_id, e.point2D_idx) for e in other.track.elements]
    assert set(read_colmap(folder)) == {im.name for im in text.images.values()}


def test_the_cap_keeps_the_same_points_in_every_image(tmp_path, scene):
    cap = 60
    rec = pycolmap.Reconstruction(export(tmp_path, scene, ColmapParams(max_points_per_image=cap)))
    assert all(im.num_points2D() <= cap for im in rec.images.values())
    # every image keeps the visible points first in one order of the map, so the images that share points keep
    # the same ones: most of what is kept is tracked
    # measured: 98 % of the cap; 10 % with a cap drawn anew per image
    assert sum(im.num_points2D() for im in rec.images.values()) >= 0.8 * len(rec.images) * cap


def test_the_capped_points_are_the_first_visible_ones_of_the_fixed_order(tmp_path, scene):
    """The writer searches the map in its fixed order a chunk at a time and stops at the cap: what it keeps is
    what a test of every point would keep. Far points that no keyframe sees make each keyframe see under 1/8 of
    the map, so the search runs past its first chunk (8 x the cap)."""
    _, xyz, rgb, depths, cameras = scene
    far = np.random.default_rng(1).normal(size=(10 * len(xyz), 3)) + 1000.0
    points = np.concatenate([xyz, far])
    cap = 20
    writer = ColmapWriter(tmp_path, points, np.zeros((len(points), 3), np.uint8),
                          ColmapParams(max_points_per_image=cap))
    for k in KEYFRAMES:
        writer.add(cameras[k], depths[k])
    rank = np.argsort(writer._order)  # each point's place in the writer's fixed order
    for (im, seen), k in zip(writer._images, KEYFRAMES):
        kept = seen.result()  # found on the writer's thread
        every = visible_points(points, np.linalg.inv(im.world_from_cam), depths[k], ColmapParams().rel_depth_tolerance)
        assert cap < len(every) < len(points) / 8
        np.testing.assert_array_equal(kept, np.sort(every[np.argsort(rank[every])[:cap]]))


def test_a_model_without_map_points_is_read_too(tmp_path, scene):
    """Cameras and no points (a map with no fused points yet): the images have no 2D points, points3D is empty."""
    _, _, _, depths, cameras = scene
    res = export_all(tmp_path, np.zeros((0, 3)), np.zeros((0, 3), np.uint8), depths, cameras, metric=False)
    rec = pycolmap.Reconstruction(res.colmap)
    assert rec.num_images() == len(KEYFRAMES) and rec.num_points3D() == 0
    assert all(im.num_points2D() == 0 for im in rec.images.values())


def test_points_written_a_batch_at_a_time_are_the_model_written_at_once(tmp_path, scene, monkeypatch):
    """points3D is formatted a batch of points at a time (the binary's records interleaved without a Python loop
    over points): batches of a few points write the same bytes as one batch of all of them, and COLMAP reads it."""
    whole = export(tmp_path / "whole", scene)
    monkeypatch.setattr(colmap, "TRACK_BATCH", 4 * 7)  # 7 track elements a batch: many batches, some of one point
    batched = export(tmp_path / "batched", scene)
    for name in ("points3D.txt", "points3D.bin"):
        assert (whole / name).read_bytes() == (batched / name).read_bytes()
    rec = pycolmap.Reconstruction(batched)
    assert rec.num_points3D() > len(scene[1]) // 2
    assert all(len(p.track.elements) >= 2 for p in rec.points3D.values())


def test_batches_cover_every_group_once_within_the_row_limit():
    lengths = np.array([3, 1, 5, 2, 2, 9, 1])
    ranges = list(colmap._batches(lengths, 5))
    assert [i for a, b in ranges for i in range(a, b)] == list(range(len(lengths)))
    # a group longer than the limit is a batch of its own; the others stay within it
    assert all(lengths[a:b].sum() <= 5 or b - a == 1 for a, b in ranges)
    assert ranges == [(0, 2), (2, 3), (3, 5), (5, 6), (6, 7)]
