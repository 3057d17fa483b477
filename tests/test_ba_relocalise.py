"""Relocalisation after a lost view, on the synthetic orbit with exact depth and poses: a pose from ORB features
and PnP against a keyframe (services/ba/frontend/relocalise.py), mapping's keyframe alignment started from it,
and tracking's fallback to it after blank frames. Poses against the exact trajectory."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch

from services.ba.core import se3, se3_numpy
from services.ba.core.host_arrays import as_numpy
from services.ba.core.params import FlowParams
from services.ba.frontend import motion
from services.ba.frontend.graph import GRID, KeyframeGraph, grid_intrinsics
from services.ba.frontend.params import MotionParams, RelocaliseParams
from services.ba.frontend.pnp import pnp_pose
from services.ba.frontend.relocalise import realign_keyframe
from services.ba.frontend.tracker import Reference, Tracker
from services.ba.settings import BaSettings

synth = pytest.importorskip("services.synth")
NEVER = RelocaliseParams(min_inliers=10**6)  # PnP never finds a pose: relocalisation off


@pytest.fixture(scope="module")
def world():
    return synth.SynthWorld(synth.SynthConfig(n_frames=150, width=512, height=384))  # 0.5 deg per frame


def _grey(rgb: np.ndarray, half: bool = False) -> np.ndarray:
    grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    return cv2.resize(grey, (grey.shape[1] // 2, grey.shape[0] // 2), interpolation=cv2.INTER_AREA) if half else grey


def _disparity(frame) -> torch.Tensor:
    depth = cv2.resize(frame.depth, (frame.depth.shape[1] // GRID, frame.depth.shape[0] // GRID),
                       interpolation=cv2.INTER_AREA)
    return torch.from_numpy(1.0 / depth).double()


def _errors(pose, truth: np.ndarray) -> tuple[float, float]:
    """(position error, rotation error in degrees) of a numpy or torch pose."""
    pose = as_numpy(pose)
    rot = math.degrees(float(np.linalg.norm(se3_numpy.so3_log(pose[:3, :3].T @ truth[:3, :3]))))
    return float(np.linalg.norm(pose[:3, 3] - truth[:3, 3])), rot


def _turn(world, a: int, b: int) -> float:
    return math.degrees(float(se3.so3_log(torch.from_numpy(world.poses[a][:3, :3].T @ world.poses[b][:3, :3])).norm()))


@pytest.mark.parametrize("scale", [1, 2])
def test_pnp_poses_a_view_38_frames_and_23_degrees_from_its_keyframe(world, scale):
    ref, cam = world.render(49), world.render(87)
    distance = float(np.linalg.norm(world.poses[87][:3, 3] - world.poses[49][:3, 3]))
    assert _turn(world, 49, 87) > 20 and distance > 0.5  # far beyond what flow chained frame to frame would need
    found = pnp_pose(_grey(ref.rgb, scale == 2), torch.from_numpy(world.poses[49]), _disparity(ref),
                     grid_intrinsics(ref.intrinsics), _grey(cam.rgb, scale == 2), scale=scale)
    assert found is not None and found.inliers >= 30
    trans, rot = _errors(found.pose, world.poses[87])
    assert trans < 0.03 * distance and rot < 0.5 * scale, (trans, rot, found.inliers)


def test_pnp_gives_no_pose_for_a_blank_view(world):
    ref = world.render(49)
    found = pnp_pose(_grey(ref.rgb), torch.from_numpy(world.poses[49]), _disparity(ref), grid_intrinsics(ref.intrinsics),
                     np.zeros((384, 512), np.uint8))
    assert found is None


def _graph(world, guess: torch.Tensor) -> KeyframeGraph:
    """Keyframe 49 at its exact pose and depth, keyframe 87 at ``guess``; flows start from the poses' (mapping's)."""
    ref, cam = world.render(49), world.render(87)
    graph = KeyframeGraph(grid_intrinsics(ref.intrinsics), (48, 64), FlowParams(), torch.device("cpu"))
    graph.predict_flow = True
    disparity = _disparity(ref)
    graph.append(49, ref.t_ns, _grey(ref.rgb), None, None, torch.from_numpy(world.poses[49]), disparity)
    graph.append(87, cam.t_ns, _grey(cam.rgb), None, None, guess, torch.full_like(disparity, float(disparity.median())))
    return graph


def _aligned(graph: KeyframeGraph) -> motion.MotionResult:
    """Keyframe 1 aligned to keyframe 0 as mapping does first (Frontend._align_keyframe)."""
    t = graph.targets(0, 1)
    return motion.align(graph.poses[1], graph.poses[0][None], graph.disparity[0][None], t.target[None],
                        t.confidence[None], graph.intrinsics, MotionParams())


def test_a_keyframe_after_a_lost_view_is_aligned_from_its_pnp_pose(world):
    """The camera turned 23 deg during a 20-frame blank; mapping's guess is where it was when the view was lost
    (frame 60). Flow started from that guess settles on a wrong pose that the flow barely supports; started from
    PnP it lands on the true one, and its flows are kept for the BA."""
    guess = torch.from_numpy(world.poses[60])
    graph = _graph(world, guess.clone())
    aligned = _aligned(graph)
    assert aligned.weight < RelocaliseParams().below_share * graph.disparity[0].numel()
    assert _errors(aligned.pose, world.poses[87])[1] > 3.0  # what mapping kept before
    res = realign_keyframe(graph, 1, aligned, MotionParams(), RelocaliseParams())
    trans, rot = _errors(res.pose, world.poses[87])
    assert rot < 0.3 and trans < 0.02, (trans, rot)
    assert res.weight > 2 * aligned.weight
    cached = graph.targets(0, 1)  # the flow the winning start made, not computed again from the old guess
    assert torch.equal(cached.target, graph.take_flows(0, 1)[(49, 87)].target)
    # nothing to relocalise: a well supported alignment is returned as it is, PnP never runs
    near = _graph(world, torch.from_numpy(world.poses[87]))
    kept = _aligned(near)
    assert realign_keyframe(near, 1, kept, MotionParams(), NEVER) is kept


@pytest.mark.parametrize("relocalise", [True, False])
def test_tracking_after_a_lost_view_takes_the_pnp_pose_where_the_flow_is_weak(world, relocalise):
    """Frames 50-79 go blank with the reference at keyframe 49 (mapping has nothing newer): frames 80-86, 31-37
    frames and 19-23 deg from it, are tracked against it. From the constant-velocity prediction the weak flow
    aligned them 4-20 deg off yet passing tracking's checks; with relocalisation they are within a degree."""
    ref = world.render(49)
    tracker = Tracker(MotionParams(), BaSettings().tracking_flow_params(),
                      relocalise_params=RelocaliseParams() if relocalise else NEVER)
    tracker.set_reference(Reference(49, ref.t_ns, torch.from_numpy(world.poses[49]), _disparity(ref),
                                    grid_intrinsics(ref.intrinsics), _grey(ref.rgb)))
    for i in range(50, 80):
        f = world.render(i)
        tracker.track(i, f.t_ns, _grey(f.rgb, half=True) if i < 60 else np.zeros((192, 256), np.uint8))
    worst = 0.0
    for i in range(80, 87):
        f = world.render(i)
        out = tracker.track(i, f.t_ns, _grey(f.rgb, half=True))
        assert out is not None
        worst = max(worst, _errors(out.pose, world.poses[i])[1] if out.ok else 0.0)
    if relocalise:
        assert worst < 1.5, worst
    else:
        assert worst > 3.0, worst  # the failure relocalisation is for, kept visible
