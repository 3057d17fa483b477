"""BA frontend pieces on exact synthetic geometry: motion-only alignment, two-view start, edge selection,
input validation."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from services.ba.core import se3, synthetic
from services.ba.frontend import edges, init, motion, steps
from services.ba.frontend.frames import interpolate
from services.ba.frontend.frontend import FrameInput, Frontend, KeyframeInput
from services.ba.frontend.graph import grid_intrinsics, working_intrinsics
from services.ba.frontend.params import FrontendParams, GraphParams, InitParams, MotionParams


def _rot_deg(a: torch.Tensor, b: torch.Tensor) -> float:
    return math.degrees(float(se3.so3_log(a[:3, :3].T @ b[:3, :3]).norm()))


def test_motion_only_alignment_recovers_a_perturbed_pose():
    win = synthetic.make_window(n=3, h=24, w=32, seed=4, surface="room")
    truth, prob = win.truth, win.problem
    # edges 0->2 and 1->2: camera 2 seen from two fixed keyframes with their true disparities
    rows = [int(e) for e in range(len(prob.ii)) if int(prob.jj[e]) == 2]
    start = synthetic.perturb_poses(truth.poses, 0.05, 2.0, torch.Generator().manual_seed(1))[2]
    assert float((start[:3, 3] - truth.poses[2, :3, 3]).norm()) > 0.04
    res = motion.align(start, truth.poses[prob.ii[rows]], truth.disparity[prob.ii[rows]], prob.targets[rows],
                       prob.confidence[rows], truth.intrinsics, MotionParams(iterations=10))
    assert res.ok and res.rms < 1e-6
    assert float((res.pose[:3, 3] - truth.poses[2, :3, 3]).norm()) < 1e-6
    assert _rot_deg(res.pose, truth.poses[2]) < 1e-5


def test_motion_only_alignment_stops_once_a_step_moves_nothing_and_lands_where_all_steps_do():
    """Tracking runs it on every frame of a live camera: the steps after convergence are pure cost."""
    win = synthetic.make_window(n=3, h=24, w=32, seed=4, surface="room")
    truth, prob = win.truth, win.problem
    rows = [int(e) for e in range(len(prob.ii)) if int(prob.jj[e]) == 2]
    start = synthetic.perturb_poses(truth.poses, 0.02, 1.0, torch.Generator().manual_seed(2))[2]
    args = (truth.poses[prob.ii[rows]], truth.disparity[prob.ii[rows]], prob.targets[rows], prob.confidence[rows],
            truth.intrinsics)
    early = motion.align(start, *args, MotionParams())
    every = motion.align(start, *args, MotionParams(step_tol=0.0))
    assert early.ok and every.ok and every.steps == MotionParams().iterations
    assert early.steps < every.steps
    assert float((early.pose - every.pose).abs().max()) < 1e-6


def test_motion_only_alignment_refuses_without_evidence():
    win = synthetic.make_window(n=2, h=8, w=8, seed=0, surface="room")
    t = win.problem
    res = motion.align(win.truth.poses[1], win.truth.poses[:1], win.truth.disparity[:1], t.targets[:1],
                       torch.zeros_like(t.confidence[:1]), win.truth.intrinsics, MotionParams())
    assert not res.ok
    assert torch.equal(res.pose, win.truth.poses[1])


def test_two_view_start_finds_the_motion_direction_and_depth_ratios():
    win = synthetic.make_window(n=4, h=24, w=32, seed=5, surface="room", step=0.15)
    truth, prob = win.truth, win.problem
    e = [k for k in range(len(prob.ii)) if int(prob.ii[k]) == 0 and int(prob.jj[k]) == 2][0]
    start = init.two_view(prob.targets[e].numpy(), prob.confidence[e].numpy(),
                          working_intrinsics(truth.intrinsics), InitParams(min_inliers=20))
    assert start is not None
    rel = (se3.inverse(truth.poses[0]) @ truth.poses[2]).numpy()
    direction = rel[:3, 3] / np.linalg.norm(rel[:3, 3])
    assert float(direction @ start.first_from_second[:3, 3]) > 0.999
    assert _rot_deg(torch.from_numpy(start.first_from_second), torch.from_numpy(rel)) < 0.05
    # |t| = 1, so disparity * |t_true| is the true disparity
    ratio = start.disparity / truth.disparity[0].numpy()
    seen = prob.confidence[e].numpy() > 0.5
    assert np.std(ratio[seen]) / np.mean(ratio[seen]) < 1e-3


def test_a_planar_scene_gets_the_true_motion_among_the_homography_candidates():
    """A wall or a desk leaves the essential matrix degenerate; the homography's decompositions include the true
    motion, and the start then chooses among them by BA cost."""
    from services.ba.core import projective
    h, w, f = 24, 32, 28.0
    intr = torch.tensor([f, f, (w - 1) / 2, (h - 1) / 2], dtype=torch.float64)
    pixels = projective.pixel_grid(h, w)
    rays = torch.stack([(pixels[:, 0] - intr[2]) / f, (pixels[:, 1] - intr[3]) / f, torch.ones(h * w)], -1)
    normal = torch.tensor([0.2, -0.1, 1.0], dtype=torch.float64)
    disparity = (rays @ normal / (2.0 * normal.norm()))[None]  # a tilted wall 2 m ahead: 1/z = n.r / d
    second = torch.eye(4, dtype=torch.float64)
    second[:3, :3] = se3.so3_exp(torch.tensor([0.0, math.radians(3.0), math.radians(1.0)], dtype=torch.float64))
    second[:3, 3] = torch.tensor([0.3, 0.05, 0.1])
    coords = projective.reproject(torch.eye(4, dtype=torch.float64)[None], second[None], disparity, pixels, intr,
                                  with_jacobians=False).coords.view(h, w, 2).numpy()
    views, inliers = init.homography_views(coords, np.ones((h, w)), working_intrinsics(intr),
                                           InitParams(min_inliers=20))
    assert inliers == h * w and 1 <= len(views) <= 2
    direction = (second[:3, 3] / second[:3, 3].norm()).numpy()
    best = max(views, key=lambda v: float(direction @ v.first_from_second[:3, 3]))
    assert float(direction @ best.first_from_second[:3, 3]) > 0.999 and best.model == "homography"
    assert _rot_deg(torch.from_numpy(best.first_from_second), second) < 0.05


def test_temporal_and_proximity_edges():
    assert set(edges.temporal_pairs([3, 4, 5], 1)) == {(4, 3), (3, 4), (5, 4), (4, 5)}
    params = GraphParams(proximity_max_flow=5.0, proximity_max_edges=2, proximity_nms=1)
    cands = [0, 1, 2, 5, 6]
    flow = torch.tensor([4.0, 1.0, 1.5, 2.0, 9.0])
    pairs = edges.proximity_pairs(10, cands, flow, params)
    # 1 is best; 2 and 0 are suppressed by it (nms 1); 5 is next; 6 is above the flow limit
    assert set(pairs) == {(10, 1), (1, 10), (10, 5), (5, 10)}


def test_induced_flow_is_zero_for_identical_cameras_and_grows_with_motion():
    win = synthetic.make_window(n=3, h=12, w=16, seed=0, surface="room")
    poses = win.truth.poses.clone()
    poses[1] = poses[0]
    flow = edges.induced_flow(poses, win.truth.disparity, win.truth.intrinsics, torch.tensor([0, 0]),
                              torch.tensor([1, 2]))
    assert float(flow[0]) < 1e-9 and float(flow[1]) > 0.5


def test_interpolation_hits_the_endpoints_and_the_midpoint():
    a = synthetic.trajectory(2, torch.Generator().manual_seed(0), step=0.3, turn_deg=10.0)
    assert torch.allclose(interpolate(a[0], a[1], 0.0), a[0], atol=1e-12)
    assert torch.allclose(interpolate(a[0], a[1], 1.0), a[1], atol=1e-12)
    mid = interpolate(a[0], a[1], 0.5)
    assert torch.allclose(interpolate(mid, a[1], 1.0), a[1], atol=1e-12)
    assert abs(_rot_deg(a[0], mid) - _rot_deg(mid, a[1])) < 1e-9


def test_grid_intrinsics_round_trip():
    work = np.array([443.4, 443.4, 255.5, 191.5])
    grid = grid_intrinsics(work)
    assert float(grid[2]) == pytest.approx(31.5) and float(grid[3]) == pytest.approx(23.5)
    np.testing.assert_allclose(working_intrinsics(grid), work)


def _keyframe(seq: int, size=(64, 96), grid=None, codes_k=8) -> KeyframeInput:
    rng = np.random.default_rng(seq)
    h, w = size
    gh, gw = grid or (h // 8, w // 8)
    return KeyframeInput(seq, seq * 100, rng.integers(0, 255, (h, w, 3), dtype=np.uint8),
                         np.array([80.0, 80.0, w / 2 - 0.5, h / 2 - 0.5]), np.ones((gh, gw, codes_k), np.float16))


def test_bad_keyframes_are_refused_and_leave_the_graph_as_it_was():
    fe = Frontend()
    fe.add_keyframe(_keyframe(0))
    with pytest.raises(ValueError, match="codes grid"):
        fe.add_keyframe(_keyframe(1, grid=(5, 5)))
    with pytest.raises(ValueError, match="differs"):
        fe.add_keyframe(_keyframe(2, size=(72, 96)))
    with pytest.raises(ValueError, match="multiple of 8"):
        fe.add_keyframe(_keyframe(3, size=(60, 96)))
    with pytest.raises(ValueError, match="not newer"):
        fe.add_keyframe(_keyframe(0))
    assert fe.graph.seqs == [0]
    with pytest.raises(ValueError, match="already a keyframe"):
        fe.add_frame(FrameInput(0, 0, np.zeros((32, 48), np.uint8)))


def test_a_fixed_camera_watching_a_moving_object_stays_put():
    # vtest-like: the keyframe selector makes only the first and last frames keyframes; there is never parallax
    rng = np.random.default_rng(3)
    import cv2

    texture = cv2.GaussianBlur(rng.integers(0, 255, (96, 128), dtype=np.uint8), (0, 0), 1.5)
    blob = cv2.GaussianBlur(rng.integers(0, 255, (24, 16), dtype=np.uint8), (0, 0), 1.0)
    frames = []
    for n in range(12):
        image = texture.copy()
        image[40:64, 10 + 8 * n: 26 + 8 * n] = blob  # a "person" crossing the view
        frames.append(image)
    fe = Frontend()
    k = np.array([100.0, 100.0, 63.5, 47.5])
    fe.add_keyframe(KeyframeInput(0, 0, frames[0], k))
    for n in range(1, 11):
        fe.add_frame(FrameInput(n, n * 100_000_000, frames[n]))
    fe.add_keyframe(KeyframeInput(11, 1_100_000_000, frames[11], k))
    poses = fe.finish().poses
    assert len(poses.frame_seqs) == 12
    rel = np.linalg.inv(poses.poses[0]) @ poses.poses
    angles = np.degrees(np.arccos(np.clip((np.trace(rel[:, :3, :3], axis1=1, axis2=2) - 1) / 2, -1, 1)))
    assert angles.max() < 0.2  # the crossing object pulls a frame by <0.1 deg
    assert np.linalg.norm(rel[:, :3, 3], axis=1).max() < 0.01  # map units: the constant disparity is 1


def test_frames_after_the_last_keyframe_get_a_pose_at_the_end():
    """A stream that ends on ordinary frames (the source stopped before the next keyframe): every frame is posed."""
    rng = np.random.default_rng(4)
    import cv2

    texture = cv2.GaussianBlur(rng.integers(0, 255, (96, 128), dtype=np.uint8), (0, 0), 1.5)
    fe = Frontend()
    k = np.array([100.0, 100.0, 63.5, 47.5])
    fe.add_keyframe(KeyframeInput(0, 0, texture, k))
    fe.add_keyframe(KeyframeInput(1, 100_000_000, np.roll(texture, 1, axis=1), k))
    for n in range(2, 5):
        fe.add_frame(FrameInput(n, n * 100_000_000, np.roll(texture, 1, axis=1)))
    poses = fe.finish().poses
    assert sorted(poses.frame_seqs.tolist()) == [0, 1, 2, 3, 4]
    assert np.isfinite(poses.poses).all()


def test_a_ba_result_whose_keyframe_flies_off_is_refused():
    from services.ba.core.ba import BAState
    from services.ba.frontend.graph import KeyframeGraph
    from services.ba.core.params import FlowParams

    graph = KeyframeGraph(torch.tensor([50.0, 50.0, 15.5, 11.5], dtype=torch.float64), (24, 32), FlowParams(),
                          torch.device("cpu"), max_step_growth=4.0)
    poses = torch.eye(4, dtype=torch.float64).repeat(5, 1, 1)
    poses[:, 0, 3] = torch.tensor([0.0, 0.3, 0.6, 2.0, 3.4])  # turning (short steps), then driving (long ones)
    start = BAState(poses, torch.ones(5, 24, 32, dtype=torch.float64), graph.intrinsics)
    corrected = poses.clone()
    corrected[:, 0, 3] = torch.tensor([0.0, 0.35, 0.7, 2.2, 3.5])
    stamps = [0, 1, 2, 3, 4]  # keyframe times (any unit): evenly spaced here
    assert not graph._jumped(start, BAState(corrected, start.disparity, start.intrinsics), stamps)
    flown = poses.clone()
    flown[4, 0, 3] = 2.0 + 8.0  # the newest keyframe slid along its free direction
    assert graph._jumped(start, BAState(flown, start.disparity, start.intrinsics), stamps) == 4  # the one to demote
    # hand-held yaw: keyframes every 3 frames while the camera turns, 13 apart where the swing turns back; BA
    # lengthening that long step (motion-only alignment had it short) to the walking speed is no jump
    walking = torch.eye(4, dtype=torch.float64).repeat(5, 1, 1)
    walking[:, 0, 3] = torch.tensor([0.0, 0.03, 0.06, 0.09, 0.12])
    true_steps = walking.clone()
    true_steps[:, 0, 3] = torch.tensor([0.0, 0.03, 0.06, 0.19, 0.22])
    assert graph._jumped(BAState(walking, start.disparity, start.intrinsics),
                         BAState(true_steps, start.disparity, start.intrinsics), [0, 3, 6, 19, 22]) is None
    # under rotation two keyframes can start almost at one place; BA finding their true step is no jump
    turning = poses.clone()
    turning[:, 0, 3] = torch.tensor([0.0, 0.3, 0.301, 0.6, 0.9])
    grown = turning.clone()
    grown[2:, 0, 3] += 0.25
    assert graph._jumped(BAState(turning, start.disparity, start.intrinsics),
                         BAState(grown, start.disparity, start.intrinsics), stamps) is None


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
