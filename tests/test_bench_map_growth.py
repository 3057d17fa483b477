"""bench/map_growth.py on a run folder made from the synthetic world itself: depth maps and poses that are the truth
(in another similarity frame, at the working size) give the true voxel counts; depth with noise gives more."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from services.evaluation.trajectory_io import Trajectory, write_tum
from services.synth import SynthWorld
from services.synth.spec import config_from_spec

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
import map_growth  # noqa: E402

SOURCE = "synth:frames=24,width=128,height=96"
SCALE = 0.25  # the run's map is in its own units: GT = SCALE · R · x + t


def _similarity() -> tuple[np.ndarray, np.ndarray]:
    angle = np.deg2rad(30.0)
    rot = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    return rot, np.array([1.0, -2.0, 0.5])


def _run_folder(tmp: Path, world: SynthWorld, depth_noise: float) -> Path:
    rot, shift = _similarity()
    poses = []
    for i in range(len(world)):  # the estimate's frame: x = R^T (GT − t) / SCALE, so its poses and depths too
        gt = world.world_from_cam(i)
        pose = np.eye(4)
        pose[:3, :3] = rot.T @ gt[:3, :3]
        pose[:3, 3] = rot.T @ (gt[:3, 3] - shift) / SCALE
        poses.append(pose)
    write_tum(tmp / "trajectory.txt", Trajectory(world.timestamps_ns() / 1e9, np.array(poses)))
    (tmp / "camera.txt").write_text(" ".join(f"{v:.6f}" for v in world.intrinsics) + "\n")
    (tmp / "summary.json").write_text(json.dumps({"source": SOURCE}))
    (tmp / "depth").mkdir()
    rng = np.random.default_rng(0)
    for seq in range(0, len(world), 3):
        depth = world.render(seq).depth / SCALE
        depth = depth * (1 + depth_noise * rng.standard_normal(depth.shape))
        working = cv2.resize(depth.astype(np.float32), None, fx=2, fy=2, interpolation=cv2.INTER_NEAREST)
        np.savez_compressed(tmp / "depth" / f"{seq:06d}.npz", depth=working, metric=False)
    return tmp


@pytest.fixture(scope="module")
def world():
    return SynthWorld(config_from_spec(SOURCE))


def _growth(run: Path, world: SynthWorld) -> map_growth.Growth:
    poses, align = map_growth.estimated_alignment(world, run / "trajectory.txt")
    files = {int(p.stem): p for p in (run / "depth").glob("*.npz")}
    intrinsics = np.array((run / "camera.txt").read_text().split()[:4], np.float64)
    return map_growth.map_growth(world, files, poses, align, intrinsics)


def test_the_truth_in_another_frame_and_size_gives_the_true_voxels(tmp_path, world):
    growth = _growth(_run_folder(tmp_path, world, 0.0), world)
    assert list(growth.seqs) == list(range(0, len(world), 3))
    assert np.all(np.diff(growth.true) >= 0) and growth.true[-1] > growth.true[0]
    # the same cells: only voxel boundaries a quarter pixel's back-projection apart differ
    np.testing.assert_allclose(growth.estimated, growth.true, rtol=0.03)


def test_depth_noise_opens_voxels_the_truth_does_not_have(tmp_path, world):
    growth = _growth(_run_folder(tmp_path, world, 0.03), world)
    assert growth.estimated[-1] > 1.2 * growth.true[-1]  # 1.31 here; 1.00 without the noise


def test_the_command_prints_the_growth_since_a_frame(tmp_path, world, capsys):
    run = _run_folder(tmp_path, world, 0.0)
    assert map_growth.main([str(run), "--after", "9", "--rows", "4", "--markdown"]) == 0
    out = capsys.readouterr().out
    assert "| keyframe (frame) |" in out and "from frame 9 to 21" in out


def test_a_run_of_a_source_without_exact_depth_is_refused_with_how_to_fix_it(tmp_path, world):
    run = _run_folder(tmp_path, world, 0.0)
    (run / "summary.json").write_text(json.dumps({"source": "../shared/data/kitti07_160"}))
    with pytest.raises(SystemExit, match="needs a synthetic run"):
        map_growth.main([str(run)])
