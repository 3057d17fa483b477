"""BA frontend pieces on exact synthetic geometry: motion-only alignment, two-view start, edge selection,
input validation."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from services.ba.core import se3, synthetic
from services.ba.frontend import edges, init, motion
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
    pose = torch.from_numpy(res.pose)
    assert float((pose[:3, 3] - truth.poses[2, :3, 3]).norm()) < 1e-6
    assert _rot_deg(pose, truth.poses[2]) < 1e-5


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
    assert float(np.abs(early.pose - every.pose).max()) < 1e-6


def test_motion_only_alignment_refuses_without_evidence():
    win = synthetic.make_window(n=2, h=8, w=8, seed=0, surface="room")
    t = win.problem
    res = motion.align(win.truth.poses[1], win.truth.poses[:1], win.truth.disparity[:1], t.targets[:1],
                       torch.zeros_like(t.confidence[:1]), win.truth.intrinsics, MotionParams())
    assert not res.ok
    assert np.array_equal(res.pose, win.truth.poses[1].numpy())


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


@pytest.mark.parametrize("turn_deg", [0.0, 10.0, 170.0])
def test_interpolation_is_the_torch_cores_geodesic(turn_deg):
    """interpolate runs on numpy (speed); it must stay torch's se3 geodesic, from no turn to a turn of 120°."""
    a = synthetic.trajectory(2, torch.Generator().manual_seed(1), step=0.3, turn_deg=turn_deg)
    if turn_deg > 100:
        assert _rot_deg(a[0], a[1]) > 120  # the large case really turns that far
    for frac in (0.0, 0.37, 0.5, 1.0):
        expected = a[0] @ se3.exp(frac * se3.log(se3.inverse(a[0]) @ a[1]))
        got = interpolate(a[0], a[1], frac)
        assert got.dtype == a[0].dtype and torch.allclose(got, expected, atol=1e-12), (turn_deg, frac)


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


@pytest.mark.parametrize("ark_with_focal", [True, False])
def test_bas_that_refine_the_focal_use_ark_only_where_ark_with_focal(ark_with_focal):
    """Up to ``focal_until`` keyframes BA refines the focal; with ``ark_with_focal`` off those BAs solve with the
    fixed kernel (a stream's first codes come late, in a young basis; they still give the static weights), and ARK
    shapes the solve again once the focal is frozen."""
    rng = np.random.default_rng(5)
    import cv2

    texture = cv2.GaussianBlur(rng.integers(0, 255, (96, 128), dtype=np.uint8), (0, 0), 1.5)
    fe = Frontend(FrontendParams(focal_after=2, focal_until=3, ark_with_focal=ark_with_focal))
    k = np.array([100.0, 100.0, 63.5, 47.5])
    for n in range(4):
        fe.add_keyframe(KeyframeInput(n, n * 100_000_000, np.roll(texture, 2 * n, axis=1), k))
        ba = fe._ba_params(list(range(len(fe.graph))))
        refines = 2 <= len(fe.graph) <= 3
        assert ba.optimise_focal == refines, n
        assert ba.robust.use_ark and ba.robust.ark_in_solve == (ark_with_focal or not refines), n
