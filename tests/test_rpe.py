"""Relative pose error (services/evaluation/rpe.py): known answers on synthetic trajectories, evo's pair selection,
invariance to the alignment, evo's own numbers on real TUM trajectories, and ``kmvipe eval ate``'s RPE columns."""
from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np
import pytest

from services.evaluation import cli
from services.evaluation.rpe import pair_indices, relative_pose_error, rotation_angles, trajectory_rpe
from services.evaluation.trajectory_io import Trajectory, quaternion_to_rotation, read_tum, write_tum

DATA = Path(os.environ.get("KMVIPE_DATA_DIR", Path(__file__).resolve().parents[1].parent / "shared" / "data"))
FIXTURES = DATA / "tum_traj_fixtures"


def _se3(rotation: np.ndarray, translation) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = rotation, translation
    return pose


def _axis_angle(axis, degrees: float) -> np.ndarray:
    axis = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    half = np.radians(degrees) / 2
    return quaternion_to_rotation(np.array([[*(np.sin(half) * axis), np.cos(half)]]))[0]


def _ground_truth(n: int, rng: np.random.Generator) -> np.ndarray:
    """A smooth random walk of ``world_from_cam`` poses (N, 4, 4): steps of ~0.1 m and a few degrees."""
    poses = [np.eye(4)]
    for _ in range(n - 1):
        step = _se3(_axis_angle(rng.normal(size=3), rng.uniform(1, 5)), rng.normal(scale=0.1, size=3))
        poses.append(poses[-1] @ step)
    return np.stack(poses)


def _with_step_error(gt: np.ndarray, error: np.ndarray, start: np.ndarray | None = None) -> np.ndarray:
    """An estimate whose every step is the true step followed by ``error``: P_k = P_{k-1} (Q_{k-1}⁻¹ Q_k) Δ."""
    est = [gt[0] if start is None else start]
    for k in range(1, len(gt)):
        est.append(est[-1] @ np.linalg.inv(gt[k - 1]) @ gt[k] @ error)
    return np.stack(est)


def test_a_constant_error_per_step_is_the_rpe_of_every_consecutive_pair():
    rng = np.random.default_rng(0)
    gt = _ground_truth(40, rng)
    error = _se3(_axis_angle([1.0, -2.0, 0.5], 0.7), [0.03, -0.04, 0.0])  # 5 cm and 0.7 deg per step
    est = _with_step_error(gt, error, start=_se3(_axis_angle([0, 0, 1], 30), [5, 1, 2]))  # any start
    res = relative_pose_error(gt, est, delta=1)
    assert res.translation.n == res.rotation.n == 39
    np.testing.assert_array_equal(res.pairs, np.stack([np.arange(39), np.arange(1, 40)], axis=1))
    np.testing.assert_allclose(res.translation_errors, 0.05, atol=1e-12)
    np.testing.assert_allclose(res.rotation_errors_deg, 0.7, atol=1e-9)
    for name in ("rmse", "mean", "median", "min", "max"):
        assert getattr(res.translation, name) == pytest.approx(0.05, abs=1e-12)
        assert getattr(res.rotation, name) == pytest.approx(0.7, abs=1e-9)
    assert res.translation.std < 1e-12 and res.translation.sse == pytest.approx(39 * 0.05**2)


@pytest.mark.parametrize("all_pairs", [False, True])
def test_an_error_that_accumulates_over_delta_steps(all_pairs):
    """Pure translation along the path with a 1 cm per step scale error: over δ frames the error is δ cm."""
    n, delta = 31, 4
    gt = np.tile(np.eye(4), (n, 1, 1))
    gt[:, :3, 3] = np.arange(n)[:, None] * [0.2, 0.1, 0.0]
    est = _with_step_error(gt, _se3(np.eye(3), [0.01, 0.0, 0.0]))
    res = relative_pose_error(gt, est, delta=delta, all_pairs=all_pairs)
    assert res.translation.n == (n - delta if all_pairs else len(range(0, n, delta)) - 1)
    np.testing.assert_allclose(res.translation_errors, delta * 0.01, atol=1e-12)
    np.testing.assert_allclose(res.rotation_errors_deg, 0.0, atol=1e-9)


def test_pairs_by_path_length_follow_evo():
    """Steps of 0.25 m with a stop (index 3→4 does not move): consecutive pairs restart the count at each kept pose,
    all pairs take for every pose the first later one whose path length is nearest δ, within 10 %."""
    steps = np.array([0.25, 0.25, 0.25, 0.0, 0.25, 0.25, 0.25])
    positions = np.zeros((len(steps) + 1, 3))
    positions[1:, 0] = np.cumsum(steps)
    np.testing.assert_array_equal(pair_indices(positions, 0.5, "m"), [[0, 2], [2, 5], [5, 7]])
    np.testing.assert_array_equal(pair_indices(positions, 0.5, "m", all_pairs=True),
                                  [[0, 2], [1, 3], [2, 5], [3, 6], [4, 6], [5, 7]])
    np.testing.assert_array_equal(pair_indices(positions, 2, "frames"), [[0, 2], [2, 4], [4, 6]])


def test_bad_deltas_are_refused_with_the_reason():
    positions = np.zeros((10, 3))
    with pytest.raises(ValueError, match="no pose pair among 10 poses"):
        pair_indices(positions, 10)
    with pytest.raises(ValueError, match="no pose pair"):
        pair_indices(positions, 0.5, "m")  # a camera that never moves has no path
    with pytest.raises(ValueError, match="whole number of frames"):
        pair_indices(positions, 1.5)
    with pytest.raises(ValueError, match="delta_unit"):
        pair_indices(positions, 1, "s")


def test_rotation_angle_known_answers_at_small_and_large_angles():
    angles = np.array([1e-9, 1e-4, 1.0, 90.0, 179.9, 180.0])
    rotations = np.stack([_axis_angle([0.3, -1.0, 2.0], a) for a in angles])
    np.testing.assert_allclose(np.degrees(rotation_angles(rotations)), angles, rtol=1e-6, atol=1e-12)


@pytest.mark.parametrize("align", ["se3", "sim3"])
def test_rpe_does_not_depend_on_the_frame_or_scale_the_alignment_removes(align):
    rng = np.random.default_rng(1)
    gt = _ground_truth(50, rng)
    est = _with_step_error(gt, _se3(_axis_angle([0, 1, 0], 0.3), [0.0, 0.02, 0.01]))
    stamps = np.arange(50) * 0.1
    direct = relative_pose_error(gt, est, delta=3, all_pairs=True)
    moved = est.copy()
    scale = 2.5 if align == "sim3" else 1.0
    moved[:, :3, 3] *= scale
    moved = _se3(_axis_angle([1, 1, 0], 40), [3, -2, 1]) @ moved
    res = trajectory_rpe(Trajectory(stamps, gt), Trajectory(stamps + 0.001, moved), align=align, delta=3,
                         all_pairs=True)
    assert res.n_matched == 50 and res.alignment.scale == pytest.approx(1 / scale, rel=0.05)
    # a rigid change of the estimate's frame leaves every P_i⁻¹ P_j as it is; a scale is undone only as well as the
    # Sim(3) fit of the drifting positions recovers it: close, not equal
    assert res.rpe.translation.rmse == pytest.approx(direct.translation.rmse, rel=1e-9 if align == "se3" else 0.05)
    assert res.rpe.rotation.rmse == pytest.approx(direct.rotation.rmse, rel=1e-6)  # rotation: a frame change only
    unaligned = trajectory_rpe(Trajectory(stamps, gt), Trajectory(stamps, moved), align="none", delta=3,
                               all_pairs=True)
    assert unaligned.rpe.rotation.rmse == pytest.approx(direct.rotation.rmse, rel=1e-6)


EVO_CASES = [(align, delta, unit, all_pairs) for align in ("se3", "sim3")
             for delta, unit, all_pairs in ((1, "frames", False), (5, "frames", True), (0.2, "m", False),
                                            (0.2, "m", True))]


@pytest.mark.data
@pytest.mark.skipif(not FIXTURES.exists(), reason="../shared/data/tum_traj_fixtures absent")
@pytest.mark.parametrize("estimate", ["freiburg1_xyz-rgbdslam.txt", "fr2_desk_ORB_kf_mono.txt"])
def test_reproduces_evo_rpe_on_real_trajectories(estimate):
    """Our numbers against ``evo.core.metrics.RPE`` itself (test-only dependency: pip install --no-deps evo==1.38.1)
    after evo's own association and Umeyama alignment, for translation and rotation angle."""
    evo_metrics = pytest.importorskip("evo.core.metrics", reason="evo not installed")
    from evo.core import sync
    from evo.tools import file_interface

    reference = "freiburg1_xyz-groundtruth.txt" if estimate.startswith("freiburg1") else "fr2_desk_groundtruth.txt"
    for align, delta, unit, all_pairs in EVO_CASES:
        ref, est = sync.associate_trajectories(file_interface.read_tum_trajectory_file(str(FIXTURES / reference)),
                                               file_interface.read_tum_trajectory_file(str(FIXTURES / estimate)),
                                               max_diff=0.02)
        est.align(ref, correct_scale=align == "sim3")
        ours = trajectory_rpe(read_tum(FIXTURES / reference), read_tum(FIXTURES / estimate), align=align,
                              max_diff=0.02, delta=delta, delta_unit=unit, all_pairs=all_pairs).rpe
        evo_unit = evo_metrics.Unit.frames if unit == "frames" else evo_metrics.Unit.meters
        for relation, stats in ((evo_metrics.PoseRelation.translation_part, ours.translation),
                                (evo_metrics.PoseRelation.rotation_angle_deg, ours.rotation)):
            metric = evo_metrics.RPE(relation, delta, evo_unit, 0.1, all_pairs)
            metric.process_data((ref, est))
            case = f"{estimate} {align} {delta} {unit} all_pairs={all_pairs} {relation.name}"
            assert stats.n == len(metric.error), case
            for name, value in metric.get_all_statistics().items():
                assert getattr(stats, name) == pytest.approx(value, rel=1e-9, abs=1e-12), f"{case} {name}"


def test_cli_prints_rpe_beside_ate(tmp_path, capsys):
    rng = np.random.default_rng(2)
    gt = _ground_truth(20, rng)
    est = _with_step_error(gt, _se3(_axis_angle([0, 0, 1], 0.5), [0.0, 0.03, 0.04]))
    stamps = np.arange(20) * 0.1
    write_tum(tmp_path / "gt.txt", Trajectory(stamps, gt))
    write_tum(tmp_path / "est.txt", Trajectory(stamps, est))
    parser = argparse.ArgumentParser()
    cli.register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["eval", "rpe", "--gt", str(tmp_path / "gt.txt"), "--est", str(tmp_path / "est.txt"),
                              "--align", "none"])
    assert args.func(args) == 0
    out = capsys.readouterr().out
    assert "rpe pairs  19 (delta 1 frames, consecutive pairs)" in out
    rows = {line.split()[0]: [float(v) for v in line.split()[1:]] for line in out.splitlines()
            if line.split()[0] in cli.STATISTICS}
    assert set(rows) == set(cli.STATISTICS)
    for name in ("rmse", "mean", "median", "min", "max"):
        assert rows[name][1:] == pytest.approx([0.05, 0.5], abs=2e-6), name  # printed with 6 decimals
    assert rows["max"][0] > 0.05  # the ATE of the drifting estimate
    args = parser.parse_args(["eval", "ate", "--gt", str(tmp_path / "gt.txt"), "--est", str(tmp_path / "est.txt"),
                              "--delta", "50", "--delta-unit", "m"])
    assert args.func(args) == 2
    assert "gives no pose pair" in capsys.readouterr().err
