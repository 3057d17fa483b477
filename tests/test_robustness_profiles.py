"""The motion robustness suite: the profiles (services/synth/profiles.py) are the motions they claim, the bench's
cache is an image folder the sources read back, and a short hand-held profile runs end to end through the
frontend (bench/robustness.py) with every frame posed."""
from __future__ import annotations

import importlib.util
import math
import sys
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from services.evaluation.trajectory_io import read_tum
from services.synth.profiles import SYNTHETIC, profile, profile_world

BENCH = Path(__file__).resolve().parents[1] / "bench"


@pytest.fixture(scope="module")
def robustness():
    sys.path.insert(0, str(BENCH))  # bench/robustness.py imports bench/frontend.py as its sibling
    spec = importlib.util.spec_from_file_location("robustness", BENCH / "robustness.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["robustness"] = module  # its dataclasses look their module up there
    spec.loader.exec_module(module)
    yield module
    sys.path.remove(str(BENCH))
    del sys.modules["robustness"]


def _angle(a: np.ndarray, b: np.ndarray) -> float:
    """Rotation angle (degrees) between the rotations of two (4, 4) poses."""
    return math.degrees(math.acos(np.clip((np.trace(a[:3, :3].T @ b[:3, :3]) - 1) / 2, -1, 1)))


def _heading(pose: np.ndarray) -> float:
    """Compass heading (degrees) of the camera's viewing direction (its z axis in the z-up world)."""
    z = pose[:3, 2]
    return math.degrees(math.atan2(z[1], z[0]))


@pytest.mark.parametrize("rate", [0.5, 1.0, 2.0, 3.0])
def test_rotation_profiles_turn_at_their_rate(rate):
    poses = profile(f"rot{rate:g}", 120).poses
    headings = np.unwrap(np.radians([_heading(p) for p in poses]))
    assert np.degrees(np.abs(np.diff(headings))).max() == pytest.approx(rate, rel=0.05)
    steps = [_angle(poses[i], poses[i + 1]) for i in range(119)]
    assert max(steps) == pytest.approx(rate, abs=0.15)  # yaw plus the slow pitch/roll wobble
    assert np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1) == pytest.approx(0.01)


def test_turn180_turns_half_a_circle():
    poses = profile("turn180", 120).poses
    turned = np.degrees(np.unwrap(np.radians([_heading(p) for p in poses])))
    assert abs(turned[-1] - turned[0]) == pytest.approx(180.0, abs=1.0)
    assert float(poses[0, :3, 2] @ poses[-1, :3, 2]) < -0.99  # looking back where it came from


def test_pure_rotation_has_a_stretch_without_translation():
    p = profile("pure_rotation", 120)
    a, b = p.rotation_only
    assert b - a >= 20  # the "no parallax for 20+ frames"
    still = p.poses[a:b]
    assert np.abs(still[:, :3, 3] - still[0, :3, 3]).max() < 1e-12
    assert _angle(still[0], still[-1]) > 35.0
    assert np.linalg.norm(p.poses[a - 1, :3, 3] - p.poses[0, :3, 3]) > 0.3  # it walked before


def test_spin_is_rotation_only():
    p = profile("spin", 120)
    assert p.rotation_only == (0, 120)
    assert np.abs(p.poses[:, :3, 3] - p.poses[0, :3, 3]).max() < 1e-12
    assert _angle(p.poses[0], p.poses[60]) > 55.0


def test_backwards_moves_along_minus_z_of_the_camera():
    poses = profile("backwards", 120).poses
    step = np.diff(poses[:, :3, 3], axis=0)
    cos = np.einsum("ni,ni->n", step / np.linalg.norm(step, axis=1, keepdims=True), poses[:-1, :3, 2])
    assert cos.max() < -0.99  # every step goes against the viewing direction
    assert np.linalg.norm(step, axis=1) == pytest.approx(0.015)


@pytest.mark.parametrize("fov", [40, 80, 110])
def test_field_of_view_gives_the_focal(fov):
    world = profile_world(profile(f"fov{fov}", 3), 128, 96)
    assert world.intrinsics[0] == pytest.approx(64 / math.tan(math.radians(fov / 2)))
    assert world.render(0).rgb.shape == (96, 128, 3)


def _detail(rgb: np.ndarray) -> float:
    """Std (grey levels) of the fine detail of an image (H, W, 3): grey minus its 5x5 mean, without the shading."""
    grey = rgb.mean(axis=2).astype(np.float32)
    return float(np.std(grey - cv2.blur(grey, (5, 5))))


def test_low_texture_walls_keep_faint_texture():
    p = profile("low_texture", 3)
    plain = profile_world(p, 128, 96).render(1).rgb
    normal = profile_world(replace(p, wall_contrast=1.0), 128, 96).render(1).rgb
    centre = (slice(30, 66), slice(40, 88))  # the bare wall ahead
    assert _detail(plain[centre]) < 0.4 * _detail(normal[centre])
    assert _detail(plain[centre]) > 0.5  # some texture remains, as on a real wall


def test_every_profile_stays_in_the_room():
    for name in SYNTHETIC:
        profile_world(profile(name, 120), 16, 12)  # SynthWorld refuses a trajectory that leaves the room


def test_unknown_profiles_say_which_exist():
    with pytest.raises(ValueError, match="known: rot0.5"):
        profile("cartwheel")
    with pytest.raises(ValueError, match="40..110"):
        profile("fov150")


def test_cache_is_an_image_folder_the_sources_read(robustness, tmp_path):
    folder, p = robustness.cached_profile("fov80", 3, 64, 48, tmp_path)
    stamp = (folder / "profile.json").stat().st_mtime_ns
    assert robustness.cached_profile("fov80", 3, 64, 48, tmp_path)[0] == folder
    assert (folder / "profile.json").stat().st_mtime_ns == stamp  # reused, not rendered again
    gt = read_tum(folder / "groundtruth.txt")
    np.testing.assert_allclose(gt.world_from_cam, p.poses, atol=1e-8)
    assert robustness.true_focal(folder) == pytest.approx(32 / math.tan(math.radians(40)), abs=1e-5)
    frames = list(robustness.open_source(str(folder)).frames())
    assert [f.rgb.shape for f in frames] == [(48, 64, 3)] * 3


def test_hand_held_yaw_end_to_end_every_frame_posed(robustness, tmp_path):
    """rot0.5 (yaw up to 0.5 °/frame while walking), 40 frames at 320x240, no calibration: every frame posed,
    within 1.5 % of the path (0.50 % measured) and the focal within 2 % (0.0 %). rot1 is left out: it is at
    18.7 % of path here today (the bas-relief failure, docs/BENCHMARKS.md), and a test must pass on today's code."""
    row = robustness.run_profile("rot0.5", 40, 320, 240, tmp_path)
    print(row)
    assert row.posed_pct == 100.0
    assert row.ate_pct_path < 1.5
    assert row.focal_err_pct < 2.0


def test_a_spin_on_the_spot_end_to_end_keeps_its_rotations(robustness, tmp_path):
    """spin (1 °/frame on the spot, nothing but rotation), 24 frames at 512x384, no calibration: every frame posed
    and no frame's rotation off by more than 0.5 ° (0.02 ° measured). The two-view start used to take the turn's
    flow for parallax and start a map from it: 14 ° off with 62 % of the frames posed here."""
    row = robustness.run_profile("spin", 24, 512, 384, tmp_path)
    print(row)
    assert row.posed_pct == 100.0
    assert row.max_rot_err_deg < 0.5
