"""Tests of the synthetic world: exact ground truth, determinism, dynamics, oracle features, writers."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from services.common.errors import ConfigError
from services.synth import (
    LABEL_NAMES, SynthConfig, SynthWorld, backproject, label_vectors, oracle_features, project,
    sample_bilinear, static_correspondence, visible_in_j,
)
from services.common.rotations import rotation_to_quaternion as quaternion_xyzw
from services.synth.io import tum_timestamp, write_image_folder, write_video

SMALL = dict(width=160, height=120, n_frames=40, texels_per_metre=48.0)  # coarse textures: fast to build
GEOM_TOL_M = 1e-3  # metres: hit points are computed in float32, errors are ~1e-5 m


@pytest.fixture(scope="module")
def small_world() -> SynthWorld:
    return SynthWorld(SynthConfig(**SMALL))


@pytest.fixture(scope="module")
def still_objects_world() -> SynthWorld:
    """Full resolution, moving camera, nothing else moves (a static scene)."""
    return SynthWorld(SynthConfig(person=False, moved_chair=False))


def _rotation_from_xyzw(q: np.ndarray) -> np.ndarray:
    """Independent of services.synth.io: quaternion -> axis-angle -> Rodrigues."""
    xyz, w = q[:3], q[3]
    angle = 2.0 * np.arctan2(np.linalg.norm(xyz), w)
    if angle < 1e-12:
        return np.eye(3)
    k = xyz / np.linalg.norm(xyz)
    return cv2.Rodrigues(k * angle)[0]


# --- configuration, camera, determinism -----------------------------------------------------------------------
@pytest.mark.parametrize("bad", [dict(camera="drone"), dict(person_walk=(0.6, 0.2)), dict(fps=0.0), dict(width=4)])
def test_config_rejects_bad_values(bad):
    with pytest.raises(ConfigError):
        SynthConfig(**bad)


def test_same_seed_identical_arrays_other_seed_differs():
    a, b = SynthWorld(SynthConfig(**SMALL)), SynthWorld(SynthConfig(**SMALL))
    c = SynthWorld(SynthConfig(**SMALL, seed=1))
    for i in (0, 17):
        fa, fb, fc = a.render(i), b.render(i), c.render(i)
        for name in ("rgb", "depth", "labels", "instance", "dynamic", "world_from_cam", "intrinsics"):
            assert np.array_equal(getattr(fa, name), getattr(fb, name)), name
        assert fa.t_ns == fb.t_ns
        assert not np.array_equal(fa.rgb, fc.rgb)
        assert not np.array_equal(fa.world_from_cam, fc.world_from_cam)  # shake phases come from the seed


def test_frame_types_intrinsics_and_timestamps(small_world):
    f = small_world.render(3)
    h, w = SMALL["height"], SMALL["width"]
    assert f.rgb.shape == (h, w, 3) and f.rgb.dtype == np.uint8
    assert f.depth.shape == (h, w) and f.depth.dtype == np.float32 and (f.depth > 0).all()
    assert f.labels.dtype == np.int32 and f.dynamic.dtype == bool
    assert f.world_from_cam.dtype == np.float64 and f.intrinsics.dtype == np.float64
    fx, fy, cx, cy = f.intrinsics
    assert np.isclose(fx, (w / 2) / np.tan(np.deg2rad(30.0))) and fy == fx
    assert (cx, cy) == ((w - 1) / 2, (h - 1) / 2)
    assert f.t_ns == 300_000_000 and small_world.timestamps_ns().dtype == np.int64
    assert np.all(np.diff(small_world.timestamps_ns()) == 100_000_000)


def test_poses_are_rigid_and_camera_is_upright_opencv(small_world):
    poses = small_world.poses
    rot = poses[:, :3, :3]
    assert np.allclose(rot @ rot.transpose(0, 2, 1), np.eye(3), atol=1e-12)
    assert np.allclose(np.linalg.det(rot), 1.0)
    assert (rot[:, 2, 1] < -0.9).all()  # camera y (down) points to world -z
    f = small_world.render(0)
    floor, ceiling = LABEL_NAMES.index("floor"), LABEL_NAMES.index("ceiling")
    half = f.labels.shape[0] // 2
    assert (f.labels[half:] == floor).sum() > (f.labels[:half] == floor).sum()
    assert not (f.labels[half:] == ceiling).any()


def test_orbit_moves_smoothly_pan_only_rotates_static_camera_is_fixed():
    orbit = SynthWorld(SynthConfig(**SMALL)).poses
    step = np.linalg.norm(np.diff(orbit[:, :3, 3], axis=0), axis=1)
    assert step.min() > 0 and step.max() < 0.2
    pan = SynthWorld(SynthConfig(**SMALL, camera="pan", shake_translation=0.0, shake_rotation_deg=0.0)).poses
    assert np.allclose(pan[:, :3, 3], pan[0, :3, 3]) and not np.allclose(pan[:, :3, :3], pan[0, :3, :3])
    static = SynthWorld(SynthConfig(**SMALL, camera="static", person=False, moved_chair=False))
    assert all(np.array_equal(p, static.poses[0]) for p in static.poses)
    a, b = static.render(0), static.render(25)
    assert np.array_equal(a.rgb, b.rgb) and np.array_equal(a.depth, b.depth)
    assert not any(static.render(i).dynamic.any() for i in range(0, 40, 5))


def test_static_camera_changes_only_where_objects_move():
    world = SynthWorld(SynthConfig(**SMALL, camera="static"))
    a, b = world.render(0), world.render(20)
    changed = (a.rgb != b.rgb).any(axis=-1)
    assert changed.any()
    assert not (changed & ~(a.dynamic | b.dynamic)).any()


# --- geometry ground truth ------------------------------------------------------------------------------------
def test_depth_consistent_between_frames(still_objects_world):
    world = still_objects_world
    for i, j in ((0, 5), (50, 60)):
        fi, fj = world.render(i), world.render(j)
        corr = static_correspondence(fi.depth, fi.intrinsics, fi.world_from_cam, fj.world_from_cam)
        inv_j = sample_bilinear(1.0 / fj.depth.astype(np.float64), corr.uv)
        rel = np.abs(1.0 / corr.z - inv_j) / inv_j
        ok = rel[corr.in_view]
        assert corr.in_view.mean() > 0.8
        assert (ok < 1e-3).mean() > 0.9 and np.median(ok) < 1e-5
        # a point can be hidden in frame j (behind), but never in front of what frame j sees (up to creases/edges)
        in_front = corr.in_view & (1.0 / corr.z > inv_j * (1 + 1e-2))
        assert in_front.mean() < 0.01
        assert visible_in_j(corr, fj.depth).sum() == (corr.in_view & (rel <= 1e-3)).sum()


def test_backproject_project_round_trip_and_known_flow():
    rng = np.random.default_rng(0)
    intr = np.array([300.0, 310.0, 79.5, 59.5])
    pose = SynthWorld(SynthConfig(**SMALL)).poses[7]
    depth = rng.uniform(1.0, 5.0, (120, 160))
    proj = project(backproject(depth, intr, pose), intr, pose)
    v, u = np.mgrid[0:120, 0:160]
    assert np.allclose(proj.uv[..., 0], u) and np.allclose(proj.uv[..., 1], v) and np.allclose(proj.z, depth)
    moved = pose.copy()
    moved[:3, 3] += pose[:3, 0] * 0.1  # camera slides 10 cm along its own x axis
    corr = static_correspondence(np.full((120, 160), 2.0), intr, pose, moved)
    assert np.allclose(corr.flow[..., 0], -300.0 * 0.1 / 2.0) and np.allclose(corr.flow[..., 1], 0.0)
    with pytest.raises(ValueError):
        backproject(depth, intr[:3], pose)


def test_labels_consistent_with_boxes(small_world):
    sx, sy, sz = small_world.config.room_size
    for i in (0, 15, 30):
        f = small_world.render(i)
        pts = backproject(f.depth, f.intrinsics, f.world_from_cam)
        lo, hi, part_inst = small_world.part_boxes(i)
        boxes = small_world.instance_boxes(i)
        for k, box in enumerate(boxes):
            sel = f.instance == k
            assert (f.labels[sel] == box.label).all()
            p = pts[sel][:, None, :]
            parts = part_inst == k
            inside = ((p >= lo[parts] - GEOM_TOL_M) & (p <= hi[parts] + GEOM_TOL_M)).all(-1).any(-1)
            assert inside.all(), box.name
        room = f.instance < 0
        p, lab = pts[room], f.labels[room]
        names = np.array(LABEL_NAMES)[lab]
        assert set(names) <= {"floor", "wall", "ceiling"}
        assert np.abs(p[names == "floor", 2]).max() < GEOM_TOL_M
        assert np.abs(p[names == "ceiling", 2] - sz).max(initial=0) < GEOM_TOL_M
        wall = p[names == "wall"]
        to_wall = np.min(np.abs(np.stack([wall[:, 0], wall[:, 0] - sx, wall[:, 1], wall[:, 1] - sy])), axis=0)
        assert to_wall.max() < GEOM_TOL_M


def test_only_person_and_moved_chair_are_dynamic_and_they_move():
    world = SynthWorld(SynthConfig(**SMALL))
    dyn = {b.name for b in world.instance_boxes(0) if b.dynamic}
    assert dyn == {"person", "chair_moved"}
    first, last = world.instance_boxes(0), world.instance_boxes(len(world) - 1)
    for a, b in zip(first, last):
        assert np.allclose(a.lo, b.lo) != a.dynamic
    chair_end = int(np.ceil(world.config.chair_move[1] * (len(world) - 1)))
    moved = [b for b in world.instance_boxes(chair_end) if b.name == "chair_moved"][0]
    assert np.allclose(moved.lo, last[[b.name for b in last].index("chair_moved")].lo)  # then it stays
    still = SynthWorld(SynthConfig(**SMALL, person=False, moved_chair=False))
    assert not any(b.dynamic for b in still.instance_boxes(0))
    assert "person" not in {b.name for b in still.instance_boxes(0)}


def _dynamic_surface_samples(world: SynthWorld, i: int, spacing: float = 0.02) -> np.ndarray:
    """Points (N, 3) on the faces of every dynamic part, inset from the edges (world metres).

    Points within 10 cm of the floor are left out: next to a foot, a floor pixel has nearly the same depth.
    """
    lo, hi, part_inst = world.part_boxes(i)
    dynamic = np.array([inst.dynamic for inst in world.instances])
    pts = []
    for a, b in zip(lo[dynamic[part_inst]], hi[dynamic[part_inst]]):
        inset = 0.1 * (b - a)
        grids = [np.arange(a[k] + inset[k], b[k] - inset[k] + 1e-9, spacing) for k in range(3)]
        for axis in range(3):
            for plane in (a[axis], b[axis]):
                mesh = np.meshgrid(*[grids[k] if k != axis else [plane] for k in range(3)], indexing="ij")
                pts.append(np.stack([m.ravel() for m in mesh], axis=-1))
    pts = np.concatenate(pts) if pts else np.zeros((0, 3))
    return pts[pts[:, 2] > 0.1]


def test_dynamic_mask_matches_visible_moving_objects(small_world):
    h, w = SMALL["height"], SMALL["width"]
    seen_empty = seen_full = False
    for i in range(len(small_world)):
        f = small_world.render(i)
        samples = _dynamic_surface_samples(small_world, i)
        proj = project(samples, f.intrinsics, f.world_from_cam)
        uv = np.round(proj.uv).astype(np.int64, copy=False) if samples.size else np.zeros((0, 2), int)
        inside = (proj.z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        uv, z = uv[inside], proj.z[inside]
        shown = np.abs(f.depth[uv[:, 1], uv[:, 0]] - z) < 0.02 * z  # the pixel shows this sample's surface
        if shown.any():
            assert f.dynamic[uv[shown, 1], uv[shown, 0]].mean() > 0.99
        if shown.any():
            assert f.dynamic.any()
        if f.dynamic.sum() >= 20:
            assert shown.any()
        seen_empty |= not f.dynamic.any()
        seen_full |= f.dynamic.any()
        assert np.array_equal(f.dynamic, np.isin(f.labels, [LABEL_NAMES.index("person"), LABEL_NAMES.index("chair")])
                              & (f.instance >= 0) & np.isin(f.instance, [k for k, inst in enumerate(
                                  small_world.instances) if inst.dynamic]))
    assert seen_empty and seen_full


def test_dense_optical_flow_recovers_ground_truth(still_objects_world):
    """Textures must be rich enough for OpenCV DIS: its flow matches the exact flow on visible pixels."""
    a, b = still_objects_world.render(0), still_objects_world.render(2)
    corr = static_correspondence(a.depth, a.intrinsics, a.world_from_cam, b.world_from_cam)
    vis = visible_in_j(corr, b.depth)
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    flow = dis.calc(cv2.cvtColor(a.rgb, cv2.COLOR_RGB2GRAY), cv2.cvtColor(b.rgb, cv2.COLOR_RGB2GRAY), None)
    epe = np.linalg.norm(flow - corr.flow, axis=-1)[vis]
    assert np.linalg.norm(corr.flow, axis=-1)[vis].mean() > 2.0  # the test needs real motion
    assert np.median(epe) < 0.3 and (epe < 1.0).mean() > 0.85


# --- oracle features ------------------------------------------------------------------------------------------
def test_oracle_features_retrieve_labels(small_world):
    labels = small_world.render(5).labels
    vecs = label_vectors(len(LABEL_NAMES), 32, seed=0)
    assert vecs.shape == (len(LABEL_NAMES), 32) and vecs.dtype == np.float32
    assert np.allclose(np.linalg.norm(vecs, axis=1), 1.0, atol=1e-6)
    assert np.array_equal(vecs, label_vectors(len(LABEL_NAMES), 32, seed=0))

    def accuracy(noise: float) -> float:
        feats = oracle_features(labels, vecs, noise, np.random.default_rng(1))
        assert feats.shape == (*labels.shape, 32) and feats.dtype == np.float32
        assert np.allclose(np.linalg.norm(feats, axis=-1), 1.0, atol=1e-5)
        return float(((feats @ vecs.T).argmax(-1) == labels).mean())

    assert accuracy(0.0) == 1.0
    assert accuracy(0.5) > 0.99
    assert accuracy(10.0) < 0.5  # the check can fail: heavy noise destroys retrieval
    with pytest.raises(ValueError):
        oracle_features(labels, vecs[:3], 0.1, np.random.default_rng(0))


# --- writers --------------------------------------------------------------------------------------------------
def test_quaternion_xyzw_round_trip():
    rng = np.random.default_rng(0)
    rotvecs = [rng.normal(size=3) for _ in range(20)] + [np.array([np.pi, 0, 0]), np.array([0, np.pi, 0]),
                                                           np.array([0, 0, np.pi]), np.zeros(3)]
    for w in rotvecs:
        r = cv2.Rodrigues(w)[0]
        q = quaternion_xyzw(r)
        assert q[3] >= 0 and np.isclose(np.linalg.norm(q), 1.0)
        assert np.allclose(_rotation_from_xyzw(q), r, atol=1e-9)
    assert np.allclose(quaternion_xyzw(cv2.Rodrigues(np.array([0, 0, 0.5]))[0]), [0, 0, np.sin(0.25), np.cos(0.25)])


def test_tum_timestamp_is_exact():
    assert tum_timestamp(0) == "0.000000" and tum_timestamp(1_500_000_000) == "1.500000"
    assert tum_timestamp(1_305_031_102_175_304_000) == "1305031102.175304"


def test_image_folder_round_trip(tmp_path):
    cfg = SynthConfig(width=64, height=48, texels_per_metre=32.0, n_frames=6, t0_ns=1_305_031_102_000_000_000)
    world = SynthWorld(cfg)
    out = write_image_folder(world, tmp_path / "seq", n_frames=4)

    def rows(name):
        return [ln.split() for ln in (out / name).read_text().splitlines() if ln and not ln.startswith("#")]

    rgb_rows, depth_rows, gt_rows = rows("rgb.txt"), rows("depth.txt"), rows("groundtruth.txt")
    assert len(rgb_rows) == len(depth_rows) == len(gt_rows) == 4
    for i, (rgb_row, depth_row, gt_row) in enumerate(zip(rgb_rows, depth_rows, gt_rows)):
        frame = world.render(i)
        assert rgb_row[0] == depth_row[0] == gt_row[0]
        assert abs(float(gt_row[0]) * 1e9 - frame.t_ns) < 1e3
        rgb = cv2.cvtColor(cv2.imread(str(out / rgb_row[1])), cv2.COLOR_BGR2RGB)
        assert np.array_equal(rgb, frame.rgb)
        depth16 = cv2.imread(str(out / depth_row[1]), cv2.IMREAD_UNCHANGED)
        assert depth16.dtype == np.uint16 and np.abs(depth16 / 5000.0 - frame.depth).max() <= 1e-4 + 1e-7
        values = np.array(gt_row[1:], float)
        assert np.allclose(values[:3], frame.world_from_cam[:3, 3], atol=1e-8)
        assert np.allclose(_rotation_from_xyzw(values[3:]), frame.world_from_cam[:3, :3], atol=1e-8)


def test_video_writer_round_trip(tmp_path):
    world = SynthWorld(SynthConfig(width=64, height=48, texels_per_metre=32.0, n_frames=5))
    path = write_video(world, tmp_path / "synth.avi", fps=10)
    cap = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, img = cap.read()
        if not ok:
            break
        frames.append(cv2.cvtColor(img, cv2.COLOR_BGR2RGB))
    cap.release()
    assert len(frames) == 5 and frames[0].shape == (48, 64, 3)
    assert np.abs(frames[2].astype(float) - world.render(2).rgb).mean() < 12.0  # MJPG is lossy
    with pytest.raises(ValueError):
        write_video(world, tmp_path / "synth.gif")
