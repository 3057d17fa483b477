"""What the bridge keeps of the trajectory: one transform per frame in frame order, the path of every frame's
latest pose, tracked poses never over mapped ones, a new session starting afresh."""
from __future__ import annotations

import numpy as np

from services.ros2.core.trajectory import Trajectory, subsample


def poses(*offsets: float) -> np.ndarray:
    out = np.tile(np.eye(4), (len(offsets), 1, 1))
    out[:, 0, 3] = offsets
    return out


def test_each_frame_is_sent_once_in_order():
    traj = Trajectory()
    first = traj.update(np.array([0]), np.array([10]), poses(0.0), tracked=True)
    assert first.seqs.tolist() == [0] and first.stamps_ns.tolist() == [10]
    # mapping revises 0 and brings 1 and 2 (never tracked): only 1 and 2 are new
    new = traj.update(np.array([2, 0, 1]), np.array([30, 10, 20]), poses(2.5, 0.5, 1.5), tracked=False)
    assert new.seqs.tolist() == [1, 2] and new.stamps_ns.tolist() == [20, 30]
    np.testing.assert_array_equal(new.world_from_cam[:, 0, 3], [1.5, 2.5])
    assert traj.update(np.array([1]), np.array([20]), poses(9.0), tracked=True).seqs.size == 0


def test_the_path_keeps_mapped_poses_over_later_tracked_ones():
    traj = Trajectory()
    traj.update(np.array([0, 1]), np.array([10, 20]), poses(0.0, 1.0), tracked=False)
    traj.update(np.array([1]), np.array([20]), poses(7.0), tracked=True)  # late tracking pose of a mapped frame
    traj.update(np.array([2]), np.array([30]), poses(2.0), tracked=True)
    assert traj.changed
    stamps, path = traj.take_path()
    assert stamps.tolist() == [10, 20, 30] and path[:, 0, 3].tolist() == [0.0, 1.0, 2.0]
    assert not traj.changed


def test_a_new_session_starts_a_new_trajectory():
    traj = Trajectory()
    traj.update(np.array([0, 1, 2]), np.array([1, 2, 3]), poses(0.0, 1.0, 2.0), tracked=False, session="a")
    new = traj.update(np.array([0]), np.array([5]), poses(4.0), tracked=True, session="b")
    assert new.seqs.tolist() == [0]  # seq 0 again, in the new world
    assert traj.take_path()[0].tolist() == [5]


def test_subsample_spreads_evenly_and_keeps_small_sets_whole():
    assert subsample(5, 10).tolist() == [0, 1, 2, 3, 4]
    picked = subsample(1000, 10)
    assert len(picked) == 10 and picked[0] == 0 and picked[-1] == 999
    assert np.all(np.diff(picked) >= 100)
