"""The BA frontend under hand-held motion, on exact synthetic geometry: a turn on the spot starts a map of
rotations, steps are judged by speed, and the first keyframe out of a turn is linked to it."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from services.ba.core import se3, synthetic
from services.ba.frontend import init, steps
from services.ba.frontend.frontend import Frontend, KeyframeInput
from services.ba.frontend.graph import grid_intrinsics
from services.ba.frontend.params import FrontendParams, GraphParams, InitParams, MotionParams
from tests.test_ba_frontend import _rot_deg


def _profile_graph(name: str, seqs: list[int]):
    """A KeyframeGraph holding frames ``seqs`` of a motion profile (256x192) as keyframes, and the world."""
    import cv2
    from services.ba.core.params import FlowParams
    from services.ba.frontend.graph import KeyframeGraph
    from services.synth.profiles import profile, profile_world

    world = profile_world(profile(name, n=max(seqs) + 1), 256, 192)
    graph = KeyframeGraph(grid_intrinsics(world.intrinsics), (24, 32), FlowParams(), torch.device("cpu"))
    for seq in seqs:
        grey = cv2.cvtColor(world.render(seq).rgb, cv2.COLOR_RGB2GRAY)
        graph.append(seq, seq, grey, None, None, torch.eye(4, dtype=torch.float64), torch.ones(24, 32, dtype=torch.float64))
    return graph, world


def test_without_parallax_keyframes_keep_their_place_and_take_the_rotation_their_flow_shows():
    graph, world = _profile_graph("spin", [0, 8, 16, 24])
    init.start_static(graph)
    for k, seq in enumerate([0, 8, 16, 24]):
        truth = torch.from_numpy(np.linalg.inv(world.poses[0]) @ world.poses[seq])
        assert _rot_deg(graph.poses[k], truth) < 0.3, (seq, _rot_deg(graph.poses[k], truth))
        assert float(graph.poses[k][:3, 3].norm()) == 0.0


def _flow(graph, i: int, j: int):
    t = graph.targets(i, j)
    return t.target.numpy(), t.confidence.numpy()


def test_translation_is_told_from_a_turn_on_the_spot_by_the_flow_it_leaves_above_its_noise():
    from services.ba.frontend.rotation import translates

    sigma = 1.0 / 8  # FlowParams.fb_sigma (1 working px) in grid px
    spin, _ = _profile_graph("spin", [0, 3, 6])  # 3 and 6 deg on the spot: every pixel moves, none by depth
    walk, _ = _profile_graph("rot1", [0, 3, 6])  # 1 cm/frame sideways while yawing
    intr = spin.intrinsics.numpy()
    for k in (1, 2):
        assert translates(*_flow(spin, 0, k), intr, 1, sigma, 1.5) is False
        assert translates(*_flow(walk, 0, k), walk.intrinsics.numpy(), 1, sigma, 1.5) is True
    # flow too broken to tell (confidence gone): no verdict either way
    target, confidence = _flow(spin, 0, 2)
    assert translates(target, confidence * 0.1, intr, 1, sigma, 1.5) is None


def test_a_camera_turning_on_the_spot_starts_a_map_of_rotations_not_a_two_view_one():
    from services.ba.core.params import BAParams

    graph, world = _profile_graph("spin", [0, 3, 6])
    assert init.turning(graph, InitParams())
    assert init.start_map(graph, InitParams(), BAParams(), MotionParams()) is None  # no two-view start from a turn
    walk, _ = _profile_graph("rot1", [0, 3, 6])
    assert not init.turning(walk, InitParams())


def test_keyframes_that_start_at_one_spot_may_move_a_little_without_a_jump():
    """A map of rotations (every keyframe at one place): BA moving them by a hair is no jump. The median speed
    was 0 there, any motion counted as infinite growth, and every window BA of a turn was refused."""
    from services.ba.core.ba import BAState
    from services.ba.core.params import FlowParams
    from services.ba.frontend.graph import KeyframeGraph

    graph = KeyframeGraph(torch.tensor([50.0, 50.0, 15.5, 11.5], dtype=torch.float64), (24, 32), FlowParams(),
                          torch.device("cpu"), max_step_growth=4.0)
    still = torch.eye(4, dtype=torch.float64).repeat(5, 1, 1)
    disparity = torch.ones(5, 24, 32, dtype=torch.float64)  # depth 1: a hundredth of it is 0.01
    nudged = still.clone()
    nudged[:, 0, 3] = torch.tensor([0.0, 1e-4, -2e-4, 3e-4, 1e-4])
    stamps = [0, 1, 2, 3, 4]
    assert graph._jumped(BAState(still, disparity, graph.intrinsics), BAState(nudged, disparity, graph.intrinsics),
                         stamps) is None
    flown = still.clone()
    flown[4, 0, 3] = 0.5  # half the scene's depth from nothing: still a jump
    assert graph._jumped(BAState(still, disparity, graph.intrinsics), BAState(flown, disparity, graph.intrinsics),
                         stamps) == 4


def test_a_keyframe_after_frames_merged_away_is_judged_by_speed_not_step_length():
    """A live stream whose mapping fell behind merges keyframes into frames, so the next mapped keyframe may be
    several frames past the one before. At the same speed its step is several times the recent steps, and the
    plausibility check must not refuse it (a refusal replaced KITTI 07 live keyframes with a shortened prediction
    and broke the map); a step far faster than the recent speed is still refused, and the prediction that
    replaces it continues the recent motion over the whole gap."""
    fe = Frontend()
    fe.add_keyframe(KeyframeInput(0, 0, np.zeros((64, 96, 3), np.uint8), np.array([80.0, 80.0, 47.5, 31.5])))
    g = fe.graph
    second = 100_000_000  # 10 Hz frames, one keyframe per frame
    for k in range(1, 6):
        pose = torch.eye(4, dtype=torch.float64)
        pose[2, 3] = 1.0 * k  # 1 m per frame, straight ahead
        g.append(k, k * second, np.zeros((64, 96), np.uint8), None, None, pose, torch.ones(8, 12, dtype=torch.float64))
    gap = 7  # frames 6-11 merged away: keyframe 12 comes 7 frames after keyframe 5
    pose = torch.eye(4, dtype=torch.float64)
    pose[2, 3] = 5.0 + gap
    g.append(12, 12 * second, np.zeros((64, 96), np.uint8), None, None, pose, torch.ones(8, 12, dtype=torch.float64))
    k = len(g) - 1
    assert steps.plausible(g, pose, k, 4.0)  # 7 m after 7 frames at 1 m per frame; 7x the last step
    flown = pose.clone()
    flown[2, 3] = 5.0 + 5 * gap  # 5 m per frame over the gap
    assert not steps.plausible(g, flown, k, 4.0)
    predicted = steps.bounded_prediction(g, k)
    assert float(predicted[2, 3]) == pytest.approx(5.0 + gap, rel=1e-6)


def test_a_walk_after_a_turn_on_the_spot_is_judged_by_the_speed_before_the_turn():
    """Keyframes walk 1 cm per frame, then six turn on the spot: the recent steps are all still and their median
    speed 0, which refused every step of the walk that followed (pure_rotation lost its last 40 cm to zero-speed
    predictions). The walk's speed comes back at the held keyframes' mean speed and is plausible; a step far
    faster than anything before is not. A map that never moved has no speed to judge its first translation by."""
    fe = Frontend()
    fe.add_keyframe(KeyframeInput(0, 0, np.zeros((64, 96, 3), np.uint8), np.array([80.0, 80.0, 47.5, 31.5])))
    g = fe.graph
    frame = 33_000_000  # 30 Hz
    depth = torch.full((8, 12), 0.5, dtype=torch.float64)  # 2 m away
    stamps = [4, 8, 12, 16, 20, 24, 28, 32, 36]  # keyframes 1-3 walk, 4-9 turn where keyframe 3 stopped
    for n, f in enumerate(stamps, start=1):
        pose = torch.eye(4, dtype=torch.float64)
        pose[0, 3] = 0.01 * min(f, 12)
        g.append(f, f * frame, np.zeros((64, 96), np.uint8), None, None, pose, depth.clone())
    k = len(g)
    resumed = torch.eye(4, dtype=torch.float64)
    resumed[0, 3] = 0.12 + 0.01 * 8  # walking again at 1 cm per frame, 8 frames after the last turn keyframe
    g.append(44, 44 * frame, np.zeros((64, 96), np.uint8), None, None, resumed, depth.clone())
    assert steps.recent_speed(g, k) == 0.0
    assert steps.turned_on_the_spot(g, 5) and not steps.turned_on_the_spot(g, 1)  # mid-turn; walking
    assert steps.still_between(g, k - 2, k - 1) and not steps.still_between(g, k - 1, k)  # out of the turn now
    assert steps.plausible(g, resumed, k, 4.0)
    flown = resumed.clone()
    flown[0, 3] = 0.12 + 0.5  # 50 cm in 8 frames: 6x the walk
    assert not steps.plausible(g, flown, k, 4.0)

    for i in range(1, len(g)):  # the same keyframes all on the spot: a first translation sets the scale
        g.poses[i] = torch.eye(4, dtype=torch.float64)
    assert steps.never_moved(g, k) and steps.plausible(g, flown, k, 4.0)


def _walk_turn_walk(params: FrontendParams) -> tuple[Frontend, int]:
    """A frontend whose graph walked three keyframes, turned 36 deg on the spot over six, and took one step out of
    the turn (room depths, grid focal 28); returns it and the last keyframe's index."""
    fe = Frontend(params)
    fe.add_keyframe(KeyframeInput(0, 0, np.zeros((192, 256, 3), np.uint8), np.array([224.0, 224.0, 127.5, 95.5])))
    g = fe.graph
    poses = []
    for k in range(10):
        pose = torch.eye(4, dtype=torch.float64)
        pose[0, 3] = 0.1 * min(k, 2) + (0.1 if k == 9 else 0.0)
        pose[:3, :3] = se3.so3_exp(torch.tensor([0.0, math.radians(6.0 * min(max(k - 2, 0), 6)), 0.0],
                                                dtype=torch.float64))
        poses.append(pose)
    disp = 1 / synthetic.room_depth(torch.stack(poses), g.intrinsics, *g.grid_hw)
    g.poses[0], g.disparity[0] = poses[0], disp[0]
    for k in range(1, 10):
        g.append(k, k * 33_000_000, np.zeros((192, 256), np.uint8), None, None, poses[k], disp[k])
    g.predict_flow = True
    return fe, 9


def test_the_first_keyframe_out_of_a_turn_on_the_spot_is_linked_to_the_turn():
    """The keyframes of a turn on the spot have no baseline for their depth, and the walk after it keeps their
    scale only through edges to them; their rotation puts them beyond the induced-flow limit of proximity edges,
    but with the flow predicted (rotation included) what counts is the flow their depth causes (pure_rotation:
    1.8 -> 0.8 % of path). Judged by their whole induced flow, only the nearest one (6 deg) gets an edge."""
    fe, k = _walk_turn_walk(FrontendParams())
    fe._add_proximity(k)
    linked = {a for a, b in fe.graph.proximity if b == k}
    plain, k = _walk_turn_walk(FrontendParams(graph=GraphParams(proximity_overlap=0.0)))
    plain._add_proximity(k)
    assert {a for a, b in plain.graph.proximity if b == k} == {6}
    assert linked <= set(range(2, 7)) and min(linked) <= 4, linked  # at the turn's spot, 18 deg or more away
