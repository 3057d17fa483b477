"""A pose that is not a rigid transform is never published or written: ``is_rigid`` tells one from the other, ba
leaves such poses out of what it sends, and the runner ignores them (one made a KITTI run's TUM writer fail at its
end: no quaternion exists for a matrix with det R < 0)."""
from __future__ import annotations

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from services.ba.core.params import FlowParams
from services.ba.frontend.frames import FramePoses
from services.ba.frontend.graph import KeyframeGraph
from services.ba.frontend.params import MotionParams
from services.ba.frontend.updates import pose_update
from services.common.rotations import is_rigid

# the rotation block a run's first pose of KITTI frame 159 had (rows of norm 0.99, 0.67, 0.93)
SEEN = [[0.76600557, -0.61266277, -0.15016735], [-0.38482236, -0.51233331, -0.20935759],
        [0.20547902, -0.00140414, 0.90818902]]


def _poses(n: int, seed: int) -> np.ndarray:
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = Rotation.random(n, random_state=seed).as_matrix()
    poses[:, :3, 3] = np.random.default_rng(seed).normal(size=(n, 3)) * 10
    return poses


def test_rigid_transforms_pass_and_everything_else_does_not():
    good = _poses(50, 0)
    assert is_rigid(good).all() and is_rigid(good[0])
    bad = np.tile(good[:1], (5, 1, 1))
    bad[0, :3, :3] = SEEN
    bad[1, :3, :3] = -bad[1, :3, :3]  # a reflection: orthonormal, det -1
    bad[2, :3, :3] *= 1.01  # scaled
    bad[3, 0, 3] = np.nan
    bad[4, 3, :] = [0, 0, 1, 1]
    assert not is_rigid(bad).any()


def test_ba_leaves_a_pose_that_is_not_rigid_out_of_what_it_sends():
    graph = KeyframeGraph(torch.tensor([40.0, 40.0, 15.5, 11.5], dtype=torch.float64), (24, 32), FlowParams(),
                          torch.device("cpu"))
    grey = np.zeros((192, 256), np.uint8)
    for seq, pose in enumerate(_poses(3, 1)):
        graph.append(seq, seq, grey, None, None, torch.from_numpy(pose), torch.ones(24, 32, dtype=torch.float64))
    graph.poses[1][:3, :3] = torch.tensor(SEEN, dtype=torch.float64)
    update = pose_update(graph, FramePoses(MotionParams()), [0, 1, 2])
    assert update.frame_seqs.tolist() == [0, 2] and is_rigid(update.poses).all()
