"""The frame-rate tracker on the synthetic world: a reference keyframe with its exact pose and depth, frames
after it tracked at the half size frames arrive in; poses against the exact trajectory."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from services.ba.core import se3_numpy as se3
from services.ba.core.host_arrays import as_numpy
from services.ba.frontend.graph import GRID, grid_intrinsics
from services.ba.frontend.params import MotionParams
from services.ba.settings import BaSettings
from services.ba.frontend.carried_depth import propagate_disparity
from services.ba.frontend.tracker import Reference, Tracker

synth = pytest.importorskip("services.synth")
TRACKING_FLOW = BaSettings().tracking_flow_params()  # as the ba service tracks


def _grey(rgb: np.ndarray, half: bool) -> np.ndarray:
    grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    return cv2.resize(grey, (grey.shape[1] // 2, grey.shape[0] // 2), interpolation=cv2.INTER_AREA) if half else grey


def _reference(world, i: int) -> Reference:
    f = world.render(i)
    depth = cv2.resize(f.depth, (f.depth.shape[1] // GRID, f.depth.shape[0] // GRID), interpolation=cv2.INTER_AREA)
    return Reference(i, f.t_ns, world.poses[i].astype(np.float64), (1.0 / depth).astype(np.float64),
                     as_numpy(grid_intrinsics(f.intrinsics)), _grey(f.rgb, half=False))


def _errors(pose: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    rot = math.degrees(float(np.linalg.norm(se3.so3_log(pose[:3, :3].T @ truth[:3, :3]))))
    return float(np.linalg.norm(pose[:3, 3] - truth[:3, 3])), rot


def test_frames_after_a_reference_are_tracked_to_the_exact_trajectory():
    world = synth.SynthWorld(synth.SynthConfig(n_frames=60, width=512, height=384))
    tracker = Tracker(MotionParams(), TRACKING_FLOW)
    assert tracker.track(1, 0, _grey(world.render(1).rgb, half=True)) is None  # no map yet: no pose
    tracker.set_reference(_reference(world, 0))
    step = float(np.linalg.norm(world.poses[5, :3, 3] - world.poses[0, :3, 3]))
    assert step > 0.05  # the frames really move away from the reference
    for i in range(1, 6):
        f = world.render(i)
        out = tracker.track(i, f.t_ns, _grey(f.rgb, half=True))
        assert out is not None and out.ok and out.ref_seq == 0
        trans, rot = _errors(out.pose, world.poses[i])
        assert trans < 0.05 * step + 2e-3 and rot < 0.3, (i, trans, rot)


def test_a_frame_without_texture_stays_at_the_constant_velocity_prediction():
    world = synth.SynthWorld(synth.SynthConfig(n_frames=60, width=512, height=384))
    tracker = Tracker(MotionParams(), TRACKING_FLOW)
    tracker.set_reference(_reference(world, 0))
    for i in (1, 2):
        f = world.render(i)
        tracker.track(i, f.t_ns, _grey(f.rgb, half=True))
    f = world.render(3)
    guess = tracker.predict(f.t_ns)
    out = tracker.track(3, f.t_ns, np.zeros((192, 256), np.uint8))
    assert out is not None and not out.ok  # a blank frame carries no motion evidence: the tracker invents none
    trans, rot = _errors(out.pose, guess)
    assert trans < 1e-3 and rot < 0.05


@pytest.mark.parametrize("speed_share, refused", [(1.0, False), (0.05, True)])
def test_a_tracked_pose_beyond_mappings_speed_is_refused_for_the_prediction(speed_share, refused):
    """Flow that holds can still land a frame far along what its view barely constrains (PnP on a view the
    synthetic person fills: 17,000 map units off). A pose farther from the reference than max_speed_growth x
    mapping's speed allows is refused: the frame keeps the prediction. At the camera's true speed nothing is."""
    world = synth.SynthWorld(synth.SynthConfig(n_frames=60, width=512, height=384))
    step = float(np.linalg.norm(world.poses[5, :3, 3] - world.poses[0, :3, 3]))
    true_speed = step / (world.render(5).t_ns - world.render(0).t_ns)
    tracker = Tracker(MotionParams(), TRACKING_FLOW)
    tracker.set_reference(_reference(world, 0)._replace(speed=speed_share * true_speed))
    for i in range(1, 4):
        f = world.render(i)
        guess = tracker.predict(f.t_ns)
        out = tracker.track(i, f.t_ns, _grey(f.rgb, half=True))
        assert out.ok != refused and out.refused == refused, i
        trans, rot = _errors(out.pose, guess if refused else world.poses[i])
        assert trans < (1e-9 if refused else 0.05 * step + 2e-3) and rot < (1e-6 if refused else 0.3), (i, trans, rot)


def test_depth_carried_to_a_new_keyframe_matches_its_own():
    world = synth.SynthWorld(synth.SynthConfig(n_frames=60, width=512, height=384, person=False, moved_chair=False))
    a, b = _reference(world, 0), _reference(world, 4)
    carried, known = propagate_disparity(a.pose, b.pose, a.disparity, a.intrinsics)
    rel = (np.abs(carried - b.disparity) / b.disparity)[known > 0]
    assert carried.shape == b.disparity.shape and float(known.mean()) > 0.6
    assert float(np.median(rel)) < 0.03 and float((rel < 0.1).mean()) > 0.85


def test_a_promoted_keyframe_keeps_tracking_on_the_exact_trajectory():
    """Mapping never answers: tracking moves its reference to each keyframe it aligned itself."""
    world = synth.SynthWorld(synth.SynthConfig(n_frames=60, width=512, height=384, person=False, moved_chair=False))
    tracker = Tracker(MotionParams(), TRACKING_FLOW)
    tracker.set_reference(_reference(world, 0))
    path = float(np.linalg.norm(world.poses[12, :3, 3] - world.poses[0, :3, 3]))
    for i in range(1, 13):
        f = world.render(i)
        out = tracker.track(i, f.t_ns, _grey(f.rgb, half=True))
        assert out is not None and out.ok
        if i % 3 == 0:
            tracker.promote(i, f.t_ns, _grey(f.rgb, half=False), out.pose)
    assert tracker.reference.seq == 12
    trans, rot = _errors(out.pose, world.poses[12])
    assert trans < 0.05 * path and rot < 1.0, (trans, rot)
    tracker.set_reference(_reference(world, 6))  # mapping two keyframes behind: the carried-over one stays
    assert tracker.reference.seq == 12
    tracker.set_reference(_reference(world, 9))  # older than the carried-over one: never a step back
    assert tracker.reference.seq == 12
    tracker.set_reference(_reference(world, 12))  # mapping holds tracking's newest: mapping's wins
    assert tracker.reference.seq == 12 and tracker.reference.known is None


def test_a_keyframe_mapping_keeps_up_with_is_not_promoted():
    world = synth.SynthWorld(synth.SynthConfig(n_frames=60, width=512, height=384, person=False, moved_chair=False))
    tracker = Tracker(MotionParams(), TRACKING_FLOW)
    tracker.set_reference(_reference(world, 0))
    tracker.promote(0, 0, _reference(world, 0).image, world.poses[0])
    f = world.render(3)
    out = tracker.track(3, f.t_ns, _grey(f.rgb, half=True))
    tracker.promote(3, f.t_ns, _grey(f.rgb, half=False), out.pose)  # mapping holds keyframe 0, the one before
    assert tracker.reference.seq == 0


def test_before_the_map_frames_get_their_rotation_and_no_translation():
    """A monocular camera has no translation until there is parallax, but its rotation is observable: before the
    map starts the first frame is the world (identity) and each later one gets the rotation that maps the first
    frame's bearings onto its own (rotating on the spot: the exact rotation to a fraction of a degree)."""
    from services.synth.profiles import profile, profile_world
    world = profile_world(profile("spin", n=20), 256, 192)
    tracker = Tracker(MotionParams(), TRACKING_FLOW)
    for i in range(0, 13, 3):
        f = world.render(i)
        small = _grey(f.rgb, half=True)
        k = np.array([f.intrinsics[0] / 2, f.intrinsics[1] / 2, (f.intrinsics[2] + 0.5) / 2 - 0.5,
                      (f.intrinsics[3] + 0.5) / 2 - 0.5])
        out = tracker.track(i, f.t_ns, small, k)
        assert out is not None and not out.ok and out.ref_seq == -1  # provisional: never anchored or promoted
        assert np.array_equal(out.pose[:3, 3], np.zeros(3))
        truth = np.linalg.inv(world.poses[0]) @ world.poses[i]
        _, rot = _errors(out.pose, truth)
        turned = math.degrees(math.acos(np.clip((np.trace(truth[:3, :3]) - 1) / 2, -1, 1)))
        print(f"frame {i}: turned {turned:.2f} deg, provisional rotation error {rot:.3f} deg")
        assert rot < 0.05 * turned + 0.1
    tracker.set_reference(_reference(world, 12))  # the map started: tracking proper from now on
    out = tracker.track(13, world.render(13).t_ns, _grey(world.render(13).rgb, half=True), k)
    assert out.ref_seq == 12


def test_a_carried_over_reference_is_corrected_by_what_mapping_found():
    """Mapping behind: tracking promoted its own keyframes from a reference that mapping has since refined (here
    the start reference was 5 cm off; its depth was right). When mapping's pose of keyframe 3 arrives, the
    carried-over reference moves by the difference between mapping's and tracking's pose of keyframe 3, so the
    next frame is tracked on the exact trajectory again; the same reference again changes nothing."""
    world = synth.SynthWorld(synth.SynthConfig(n_frames=60, width=512, height=384, person=False, moved_chair=False))
    tracker = Tracker(MotionParams(), TRACKING_FLOW)
    off = np.eye(4)
    off[:3, 3] = [0.05, 0.0, 0.0]
    start = _reference(world, 0)
    tracker.set_reference(start._replace(pose=off @ start.pose))
    for i in range(1, 10):
        f = world.render(i)
        out = tracker.track(i, f.t_ns, _grey(f.rgb, half=True))
        if i % 3 == 0:
            tracker.promote(i, f.t_ns, _grey(f.rgb, half=False), out.pose)
    assert tracker.reference.seq == 9
    f = world.render(10)
    before, _ = _errors(tracker.track(10, f.t_ns, _grey(f.rgb, half=True)).pose, world.poses[10])
    tracker.set_reference(_reference(world, 3))  # mapping's keyframe 3: two behind the newest
    assert tracker.reference.seq == 9  # still the carried-over one, moved
    corrected = tracker.reference.pose.copy()
    tracker.set_reference(_reference(world, 3))
    np.testing.assert_allclose(tracker.reference.pose, corrected, rtol=1e-12, atol=1e-12)
    f = world.render(11)
    out = tracker.track(11, f.t_ns, _grey(f.rgb, half=True))
    trans, rot = _errors(out.pose, world.poses[11])
    print(f"{before:.3f} m off before mapping's correction, {trans:.4f} m after")
    assert before > 0.04 and trans < 0.025 and rot < 0.5


def test_corrections_in_a_row_keep_every_pose_on_so3():
    """Mapping three keyframes behind for 36 keyframes in a row, each of its poses and each of tracking's a little
    off: every correction multiplies the promoted poses by a fix computed from them. Unchecked, rounding off SO(3)
    doubled with each one (2e-6 after 36 here; a KITTI stream's last prediction had det R < 0)."""
    world = synth.SynthWorld(synth.SynthConfig(n_frames=40, width=256, height=192, person=False, moved_chair=False))
    tracker = Tracker(MotionParams(), TRACKING_FLOW)
    tracker.set_reference(_reference(world, 0))
    noise = np.random.default_rng(0)

    def nudged(pose: np.ndarray) -> np.ndarray:
        return pose @ se3.exp(noise.normal(size=6) * 0.01)

    def off_so3(pose: np.ndarray) -> float:
        rot = pose[:3, :3]
        return float(np.abs(rot.T @ rot - np.eye(3)).max())

    for k in range(1, 40):
        f = world.render(k)
        tracker.promote(k, f.t_ns, _grey(f.rgb, half=False), nudged(world.poses[k].astype(np.float64)))
        if k >= 4:
            ref = _reference(world, k - 3)
            tracker.set_reference(ref._replace(pose=nudged(ref.pose)))
    worst = max(off_so3(p) for p in [*tracker._promoted.values(), tracker.reference.pose, tracker.predict(10**12)])
    assert worst < 1e-9, worst


def test_a_carried_over_chain_takes_mappings_scale_too():
    """Mapping behind, and tracking's start depth 30 % too near (its reference's disparity / 0.7): the keyframes it
    promotes and the frames after them move 0.7 of the true distance. Mapping's keyframe 3 then comes with the true
    pose and depth. A rigid correction would leave the 0.3 shortfall of keyframes 3 -> 9 in the carried-over
    reference; stretched by mapping's depth over tracking's at keyframe 3, the next frame is near the truth."""
    world = synth.SynthWorld(synth.SynthConfig(n_frames=60, width=512, height=384, person=False, moved_chair=False))
    tracker = Tracker(MotionParams(), TRACKING_FLOW)
    start = _reference(world, 0)
    tracker.set_reference(start._replace(disparity=start.disparity / 0.7))
    for i in range(1, 10):
        f = world.render(i)
        out = tracker.track(i, f.t_ns, _grey(f.rgb, half=True))
        assert out.ok
        if i % 3 == 0:
            tracker.promote(i, f.t_ns, _grey(f.rgb, half=False), out.pose)
    assert tracker.reference.seq == 9
    assert tracker._depth_scale(_reference(world, 3)) == pytest.approx(1 / 0.7, rel=0.1)
    gap = float(np.linalg.norm(world.poses[9, :3, 3] - world.poses[3, :3, 3]))
    tracker.set_reference(_reference(world, 3))
    assert tracker.reference.seq == 9
    head_off, _ = _errors(tracker.reference.pose, world.poses[9])
    f = world.render(10)
    trans, rot = _errors(tracker.track(10, f.t_ns, _grey(f.rgb, half=True)).pose, world.poses[10])
    print(f"keyframes 3 -> 9 span {gap:.3f} m; after the correction keyframe 9 is {head_off:.4f} m off, "
          f"frame 10 {trans:.4f} m")
    assert gap > 0.1 and head_off < 0.1 * gap and trans < 0.1 * gap and rot < 0.5
