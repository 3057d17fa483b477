"""Keyframe selection by DIS flow: known shifts, the synthetic world's moving and static cameras."""
from __future__ import annotations

import numpy as np
import pytest

from services.features.core.geometry import GRID_STRIDE, resize_to_working, to_grey, working_size
from services.features.core.keyframes import KeyframeParams, KeyframeSelector, grid_flow_magnitude, robust_mean

synth = pytest.importorskip("services.synth")


def _scene() -> np.ndarray:
    """A natural-looking grey image (a synthetic room view) to translate by known amounts.

    DIS needs coarse structure for large shifts; white noise alone aliases and it locks onto wrong matches.
    """
    frame = synth.SynthWorld(synth.SynthConfig(n_frames=2, person=False)).render(0)
    return to_grey(frame.rgb)


def test_known_shift_measures_shift_over_eight():
    big = _scene()
    ref = np.ascontiguousarray(big[40:280, 40:360])
    sel = KeyframeSelector(KeyframeParams(outlier_fraction=0.0))
    assert sel.observe(ref).is_keyframe  # first frame
    for shift in (4, 12, 24):
        moved = np.ascontiguousarray(big[40:280, 40 + shift : 360 + shift])
        assert sel.motion(moved) == pytest.approx(shift / GRID_STRIDE, rel=0.15)


def test_threshold_decides_and_reference_moves():
    big = _scene()
    sel = KeyframeSelector(KeyframeParams(threshold_grid_px=2.4))
    frames = [np.ascontiguousarray(big[40:280, 40 + 4 * i : 360 + 4 * i]) for i in range(12)]
    flags = [sel.observe(f).is_keyframe for f in frames]
    # 4 px per frame = 0.5 grid px per frame: a new keyframe every 5th frame (2.5 > 2.4)
    assert flags == [True, False, False, False, False, True, False, False, False, False, True, False]


def test_a_covered_lens_makes_no_keyframe_and_the_first_view_after_it_is_one():
    """Frames that show nothing (black) are never keyframes, whatever DIS makes of them; the first frame that
    shows something again is one even without motion, since the flow chained over the blank frames is lost."""
    big = _scene()
    view = np.ascontiguousarray(big[40:280, 40:360])
    frames = [view] * 3 + [np.zeros_like(view)] * 3 + [view] * 3
    sel = KeyframeSelector()
    decisions = [sel.observe(f) for f in frames]
    assert [d.is_keyframe for d in decisions] == [True, False, False, False, False, False, True, False, False]
    assert all(d.motion_grid_px == 0.0 for d in decisions[3:6])


def test_robust_mean_ignores_a_small_fast_region():
    values = np.zeros((30, 40))
    values[:5, :10] = 50.0  # 4 % of the cells move a lot
    assert robust_mean(values, 0.2) == 0.0
    assert robust_mean(values, 0.0) == pytest.approx(50.0 * 50 / 1200)


def test_grid_flow_magnitude_units():
    flow = np.zeros((60, 80, 2), np.float32)
    flow[..., 0] = 2.0  # 2 px at half working resolution = 4 working px = 0.5 grid px
    mag = grid_flow_magnitude(flow, (15, 20), flow_scale=0.5)
    assert mag.shape == (15, 20) and np.allclose(mag, 0.5)


def _gt_motion(world, i: int, j: int, size, outlier_fraction: float) -> float:
    """Robust mean grid-pixel motion i → j from exact depth and poses (static scene)."""
    import cv2

    fi, fj = world.render(i), world.render(j)
    corr = synth.static_correspondence(fi.depth, fi.intrinsics, fi.world_from_cam, fj.world_from_cam)
    flow = np.where(corr.in_view[..., None], corr.flow, 0.0).astype(np.float32)
    flow[..., 0] *= size.scale_x
    flow[..., 1] *= size.scale_y
    work = cv2.resize(flow, (size.width, size.height), interpolation=cv2.INTER_AREA)
    return robust_mean(grid_flow_magnitude(work, (size.height // 8, size.width // 8), 1.0), outlier_fraction)


def test_static_camera_with_walking_person_gives_no_new_keyframe():
    cfg = synth.SynthConfig(n_frames=40, camera="static", person=True, moved_chair=True, person_walk=(0.0, 1.0))
    world = synth.SynthWorld(cfg)
    size = working_size(cfg.height, cfg.width)
    sel = KeyframeSelector()
    dyn_fraction = []
    decisions = []
    for i in range(cfg.n_frames):
        frame = world.render(i)
        dyn_fraction.append(frame.dynamic.mean())
        decisions.append(sel.observe(to_grey(resize_to_working(frame.rgb, size))))
    assert max(dyn_fraction) > 0.03  # the person is really in view
    assert decisions[0].is_keyframe
    assert not any(d.is_keyframe for d in decisions[1:]), [round(d.motion_grid_px, 2) for d in decisions]


def test_orbiting_camera_selects_keyframes_when_motion_crosses_threshold():
    cfg = synth.SynthConfig(n_frames=60, camera="orbit", person=False, moved_chair=False)
    world = synth.SynthWorld(cfg)
    size = working_size(cfg.height, cfg.width)
    params = KeyframeParams()
    sel = KeyframeSelector(params)
    keyframes, last_kf = [], 0
    for i in range(cfg.n_frames):
        d = sel.observe(to_grey(resize_to_working(world.render(i).rgb, size)))
        if i > 0:
            gt = _gt_motion(world, last_kf, i, size, params.outlier_fraction)
            if d.is_keyframe:  # selected only when the true motion is near or above the threshold
                assert gt > 0.75 * params.threshold_grid_px, (i, gt, d.motion_grid_px)
            else:
                assert gt < 1.4 * params.threshold_grid_px, (i, gt, d.motion_grid_px)
        if d.is_keyframe:
            keyframes.append(i)
            last_kf = i
    assert 4 <= len(keyframes) <= cfg.n_frames // 2, keyframes


def test_fast_forward_driving_keeps_making_keyframes(data_dir):
    # KITTI 07 frames 45-100: straight road at ~0.8 m/frame. From a zero start, DIS against a keyframe a few
    # metres behind finds near-zero flow, and the old selector made no keyframe between frames 49 and 94.
    import cv2

    seq = data_dir / "kitti07_160" / "rgb"
    sel = KeyframeSelector(KeyframeParams())
    keyframes = []
    for n in range(45, 101):
        grey = cv2.imread(str(seq / f"{n:06d}.png"), cv2.IMREAD_GRAYSCALE)
        work = resize_to_working(grey, working_size(*grey.shape))
        if sel.observe(work).is_keyframe:
            keyframes.append(n)
    gaps = np.diff(keyframes)
    assert len(keyframes) >= 12 and gaps.max() <= 6, keyframes
