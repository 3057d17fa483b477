"""Trajectory I/O, association, Umeyama and ATE: reference values from evo, recovery on synthetic data, CLI."""
from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import numpy as np
import pytest

from services.evaluation import cli
from services.evaluation.ate import absolute_trajectory_error, associate, umeyama
from services.evaluation.trajectory_io import (Trajectory, TrajectoryFormatError, quaternion_to_rotation,
                                               read_kitti, read_tum, rotation_to_quaternion, write_kitti,
                                               write_tum)

DATA = Path(os.environ.get("KMVIPE_DATA_DIR", Path(__file__).resolve().parents[1].parent / "shared" / "data"))
FIXTURES = DATA / "tum_traj_fixtures"


def _random_rotations(n: int, rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=(n, 4))
    return quaternion_to_rotation(q)


def _random_trajectory(n: int, rng: np.random.Generator) -> Trajectory:
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = _random_rotations(n, rng)
    poses[:, :3, 3] = np.cumsum(rng.normal(size=(n, 3)), axis=0)
    return Trajectory(np.arange(n) * 0.1 + 1e9, poses)


def _cases():
    if not (FIXTURES / "expected.json").exists():
        return []
    return json.loads((FIXTURES / "expected.json").read_text())["results"]


@pytest.mark.data
@pytest.mark.skipif(not FIXTURES.exists(), reason="../shared/data/tum_traj_fixtures absent")
@pytest.mark.parametrize("case", _cases(), ids=lambda c: f"{c['estimate']}-{c['alignment']}")
def test_reproduces_evo_reference_values(case):
    ref = read_tum(FIXTURES / case["reference"])
    est = read_tum(FIXTURES / case["estimate"])
    assert len(ref.timestamps) == case["n_reference_poses"] and len(est.timestamps) == case["n_estimate_poses"]
    res = absolute_trajectory_error(ref, est, align=case["alignment"], max_diff=0.02)
    assert res.n_pairs == case["n_pairs"]
    assert res.rmse == pytest.approx(case["ate_rmse_m"], abs=1e-6)
    assert res.alignment.scale == pytest.approx(case["scale"], abs=1e-6)
    for key, value in case["stats_m"].items():
        assert getattr(res, key) == pytest.approx(value, abs=1e-6), key


def test_tum_and_kitti_round_trip(tmp_path):
    traj = _random_trajectory(20, np.random.default_rng(0))
    write_tum(tmp_path / "t.txt", traj)
    back = read_tum(tmp_path / "t.txt")
    np.testing.assert_allclose(back.timestamps, traj.timestamps, atol=1e-9)
    np.testing.assert_allclose(back.world_from_cam, traj.world_from_cam, atol=1e-8)
    write_kitti(tmp_path / "k.txt", traj)
    back = read_kitti(tmp_path / "k.txt")
    np.testing.assert_allclose(back.world_from_cam, traj.world_from_cam, rtol=1e-8, atol=1e-8)
    np.testing.assert_array_equal(back.timestamps, np.arange(20))


def test_quaternion_round_trip_and_known_answer():
    rng = np.random.default_rng(1)
    rot = _random_rotations(50, rng)
    np.testing.assert_allclose(quaternion_to_rotation(rotation_to_quaternion(rot)), rot, atol=1e-12)
    q = rotation_to_quaternion(np.diag([-1.0, -1.0, 1.0])[None])  # 180 deg about z
    np.testing.assert_allclose(np.abs(q), [[0, 0, 1, 0]], atol=1e-12)


def test_bad_file_raises(tmp_path):
    (tmp_path / "bad.txt").write_text("0 1 2 3\n")
    with pytest.raises(TrajectoryFormatError):
        read_tum(tmp_path / "bad.txt")


def test_association_nearest_with_threshold():
    ref = np.array([0.0, 1.0, 2.0, 3.0, 4.0])
    est = np.array([0.004, 2.6, 3.995])
    pairs = associate(ref, est, max_diff=0.01)
    np.testing.assert_array_equal(pairs.reference_index, [0, 4])
    np.testing.assert_array_equal(pairs.estimate_index, [0, 2])


@pytest.mark.parametrize("with_scale", [False, True])
def test_umeyama_recovers_known_similarity(with_scale):
    rng = np.random.default_rng(2)
    pts = rng.normal(size=(30, 3))
    rot = _random_rotations(1, rng)[0]
    scale = 2.5 if with_scale else 1.0
    target = scale * pts @ rot.T + np.array([1.0, -2.0, 0.5])
    al = umeyama(pts, target, with_scale)
    np.testing.assert_allclose(al.rotation, rot, atol=1e-10)
    assert al.scale == pytest.approx(scale)


def test_ate_zero_after_sim3_of_transformed_copy_and_recovers_noise():
    rng = np.random.default_rng(3)
    gt = _random_trajectory(50, rng)
    sim = np.eye(4)
    sim[:3, :3] = 0.3 * _random_rotations(1, rng)[0]
    sim[:3, 3] = [5.0, 1.0, -2.0]
    est_poses = sim @ gt.world_from_cam
    noise = rng.normal(scale=0.01, size=(50, 3))
    est_poses[:, :3, 3] += noise
    est = Trajectory(gt.timestamps + 0.001, est_poses)
    res = absolute_trajectory_error(gt, est, align="sim3", max_diff=0.01)
    assert res.n_pairs == 50 and res.alignment.scale == pytest.approx(1 / 0.3, rel=0.01)
    assert 0.5 * 0.01 * np.sqrt(3) < res.rmse < 1.5 * 0.01 * np.sqrt(3) / 0.3
    assert absolute_trajectory_error(gt, est, align="se3").rmse > 1.0


def test_cli_prints_statistics(tmp_path, capsys):
    rng = np.random.default_rng(4)
    gt = _random_trajectory(10, rng)
    write_tum(tmp_path / "gt.txt", gt)
    write_tum(tmp_path / "est.txt", gt)
    parser = argparse.ArgumentParser()
    cli.register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["eval", "ate", "--gt", str(tmp_path / "gt.txt"), "--est", str(tmp_path / "est.txt"),
                              "--align", "sim3"])
    assert args.func(args) == 0
    out = capsys.readouterr().out
    assert "pairs      10" in out and "rmse       0.000000" in out and "scale      1.000000" in out
    args = parser.parse_args(["eval", "ate", "--gt", str(tmp_path / "missing.txt"), "--est", str(tmp_path / "est.txt")])
    assert args.func(args) == 2


def test_drift_by_stretch_finds_the_scale_drift_and_the_offset_it_leaves():
    from services.evaluation.drift import drift_by_stretch

    # a circle walked three times; the estimate is exact for the first 100 poses, then its scale about the start
    # grows by 10 % per further 100 poses, all of it in a rotated, shifted, scaled frame (Sim(3) to recover)
    n = 300
    theta = np.linspace(0, 6 * np.pi, n, endpoint=False)
    ref = np.stack([np.cos(theta), np.sin(theta), 0.1 * np.sin(3 * theta)], 1) * 2.0
    growth = np.where(np.arange(n) < 100, 1.0, 1.0 + 0.1 * (np.arange(n) // 100))
    est_local = ref * growth[:, None]
    c, s = np.cos(0.3), np.sin(0.3)
    rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    est = 0.5 * est_local @ rot.T + np.array([1.0, -2.0, 0.5])

    def traj(points):
        poses = np.tile(np.eye(4), (n, 1, 1))
        poses[:, :3, 3] = points
        return Trajectory(np.arange(n, dtype=np.float64), poses)

    stretches = drift_by_stretch(traj(ref), traj(est), 100)
    assert [(s.first, s.count) for s in stretches] == [(0, 100), (100, 100), (200, 100)]
    assert [s.scale_ratio for s in stretches] == pytest.approx([1.0, 1.1, 1.2], abs=1e-9)
    # aligned on the first stretch, a point at radius r ends 10 % / 20 % of r off (|ref| is 2 m, give or take z)
    assert stretches[0].mean_error == pytest.approx(0.0, abs=1e-9)
    radius = np.linalg.norm(ref, axis=1)
    for stretch, excess in zip(stretches[1:], (0.1, 0.2)):
        part = slice(stretch.first, stretch.first + stretch.count)
        assert stretch.mean_error == pytest.approx(excess * radius[part].mean(), rel=1e-9)
    with pytest.raises(ValueError, match="at least 3"):
        drift_by_stretch(traj(ref), traj(est), 2)
