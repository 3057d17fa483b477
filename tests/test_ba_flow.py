"""Flow targets: DIS flow sampled to the 1/8 grid (cell-centre convention) and forward-backward confidence."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from services.ba.core.flow import FlowParams, dis_flow, edge_targets, flow_targets, pair_targets, to_grey


def _texture(h: int, w: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    noise = rng.random((h, w)).astype(np.float32)
    img = cv2.GaussianBlur(noise, (0, 0), 2.0)
    img = (img - img.min()) / (img.max() - img.min()) * 255
    return img.astype(np.uint8)


def _shift(img: np.ndarray, dx: float, dy: float) -> np.ndarray:
    """Content moves by (+dx, +dy): new(x + dx, y + dy) = old(x, y)."""
    m = np.float32([[1, 0, dx], [0, 1, dy]])
    return cv2.warpAffine(img, m, (img.shape[1], img.shape[0]), flags=cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_REFLECT)


def _two_views(name: str) -> list[np.ndarray]:
    """Frames 0 and 4 of a synthetic profile, grey, 256x192."""
    from services.synth.profiles import profile, profile_world

    world = profile_world(profile(name, n=5), 256, 192)
    return [cv2.cvtColor(world.render(seq).rgb, cv2.COLOR_RGB2GRAY) for seq in (0, 4)]


def _graph_of(images: list[np.ndarray], params: FlowParams, second_pose=None, **graph_attrs):
    """A keyframe graph over two 256x192 keyframes (a 32x24 grid, unit disparity), the first at the origin, the
    second at ``second_pose`` (default: the origin too); ``graph_attrs`` set on the graph before they join."""
    import torch

    from services.ba.frontend.graph import KeyframeGraph

    graph = KeyframeGraph(torch.tensor([40.0, 40.0, 15.5, 11.5], dtype=torch.float64), (24, 32), params,
                          torch.device("cpu"))
    for name, value in graph_attrs.items():
        setattr(graph, name, value)
    origin = torch.eye(4, dtype=torch.float64)
    for seq, grey, pose in zip((0, 4), images, (origin, origin if second_pose is None else second_pose)):
        graph.append(seq, seq, grey, None, None, pose, torch.ones(24, 32, dtype=torch.float64))
    return graph


def _halved(images: list[np.ndarray], params: FlowParams) -> tuple[list[np.ndarray], FlowParams]:
    """``images`` at half size and ``params`` for them (4-px cells, the forward-backward sigma in their pixels)."""
    from dataclasses import replace

    halves = [cv2.resize(image, (128, 96), interpolation=cv2.INTER_AREA) for image in images]
    return halves, replace(params, grid=params.grid // 2, fb_sigma=params.fb_sigma / 2)



def test_translation_gives_shifted_grid_targets():
    img = _texture(128, 160, seed=0)
    dx, dy = 5.5, -3.25
    out = flow_targets(img, _shift(img, dx, dy), FlowParams())
    assert out.target.shape == (16, 20, 2) and out.confidence.shape == (16, 20)
    rows, cols = np.mgrid[0:16, 0:20]
    interior = (slice(2, -2), slice(2, -2))
    # grid coordinates: a shift of s working pixels is s/8 grid pixels
    np.testing.assert_allclose(out.target[..., 0][interior], (cols + dx / 8)[interior], atol=0.05)
    np.testing.assert_allclose(out.target[..., 1][interior], (rows + dy / 8)[interior], atol=0.05)
    assert out.confidence[interior].mean() > 0.8


def test_half_resolution_targets_are_in_the_same_grid_coordinates():
    """Non-keyframes' flow runs at half size with 4-px cells: the grid targets must not move (cell centres map)."""
    img = _texture(128, 160, seed=3)
    dx, dy = 6.0, 2.0
    moved = _shift(img, dx, dy)
    half = lambda a: cv2.resize(a, (80, 64), interpolation=cv2.INTER_AREA)  # noqa: E731
    out = flow_targets(half(img), half(moved), FlowParams(grid=4, fb_sigma=0.5))
    rows, cols = np.mgrid[0:16, 0:20]
    interior = (slice(2, -2), slice(2, -2))
    np.testing.assert_allclose(out.target[..., 0][interior], (cols + dx / 8)[interior], atol=0.05)
    np.testing.assert_allclose(out.target[..., 1][interior], (rows + dy / 8)[interior], atol=0.05)


def test_pair_targets_equal_two_single_edge_calls():
    img = _texture(96, 128, seed=4)
    other = _shift(img, -3.0, 1.5)
    there, back = pair_targets(img, other, FlowParams())
    for got, want in ((there, flow_targets(img, other, FlowParams())), (back, flow_targets(other, img, FlowParams()))):
        np.testing.assert_allclose(got.target, want.target, atol=1e-5)
        np.testing.assert_allclose(got.confidence, want.confidence, atol=1e-5)


def test_targets_are_float64_block_means_of_each_pixels_landing_point_and_check():
    """The grid targets and confidences, recomputed pixel by pixel from the two DIS flows with numpy in float64:
    they are block means (summed in float64: float32 sums moved a two-lap orbit's ATE by 30 %)."""
    img = _texture(96, 128, seed=5)
    other = _shift(img, 2.5, -1.75)
    params = FlowParams()
    out = flow_targets(img, other, params)
    fwd = out.flow.astype(np.float64)
    bwd = dis_flow(other, img, params).astype(np.float32)
    rows, cols = np.mgrid[0:96, 0:128].astype(np.float64)
    land_x, land_y = cols + fwd[..., 0], rows + fwd[..., 1]
    back = cv2.remap(bwd, land_x.astype(np.float32), land_y.astype(np.float32), cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE).astype(np.float64)
    err2 = (fwd[..., 0] + back[..., 0]) ** 2 + (fwd[..., 1] + back[..., 1]) ** 2
    inside = (land_x >= -0.5) & (land_x <= 127.5) & (land_y >= -0.5) & (land_y <= 95.5)
    conf = np.exp(-0.5 * err2 / params.fb_sigma**2) * inside
    blocks = lambda x: x.reshape(12, 8, 16, 8).mean(axis=(1, 3))  # noqa: E731
    np.testing.assert_allclose(out.target[..., 0], (blocks(land_x) + 0.5) / 8 - 0.5, atol=2e-6)
    np.testing.assert_allclose(out.target[..., 1], (blocks(land_y) + 0.5) / 8 - 0.5, atol=2e-6)
    np.testing.assert_allclose(out.confidence, blocks(conf), atol=1e-6)


def test_inconsistent_region_gets_low_confidence():
    img = _texture(128, 160, seed=1)
    other = _shift(img, 4.0, 0.0)
    other[40:88, 56:104] = _texture(48, 48, seed=2)  # content that is not in image i
    out = flow_targets(img, other, FlowParams())
    inside = out.confidence[5:11, 7:13].mean()  # grid cells covering the replaced block
    outside = np.concatenate([out.confidence[1:4, 2:-2].ravel(), out.confidence[-4:-1, 2:-2].ravel()]).mean()
    assert inside < 0.6 and outside > 0.95, (inside, outside)
    # cells whose 8x8 block half leaves image j (content moves right by 4 px) get half confidence
    np.testing.assert_allclose(out.confidence[1:-1, -1], 0.5, atol=0.05)


def test_rgb_input_and_bad_sizes():
    rgb = np.stack([_texture(64, 64, 3)] * 3, -1)
    assert to_grey(rgb).shape == (64, 64)
    with pytest.raises(ValueError):
        flow_targets(rgb[:60], rgb[:60], FlowParams())
    with pytest.raises(ValueError):
        to_grey(rgb.astype(np.float32))


def test_edge_targets_stack_every_edge_and_share_the_flows_of_opposite_edges():
    base = _texture(64, 96, seed=5)
    imgs = [base, _shift(base, 2.0, 1.0), _shift(base, 4.0, 2.0)]
    edges = [(0, 1), (1, 0), (1, 2), (2, 0)]
    targets, confidence = edge_targets(imgs, edges, FlowParams())
    assert targets.shape == (4, 8, 12, 2) and confidence.shape == (4, 8, 12)
    for e, (i, j) in enumerate(edges):
        want = flow_targets(imgs[i], imgs[j], FlowParams())
        np.testing.assert_allclose(targets[e], want.target, atol=1e-5)
        np.testing.assert_allclose(confidence[e], want.confidence, atol=1e-5)


@pytest.mark.parametrize("stride", [None, 4])
def test_patch_stride_reaches_dis_and_both_strides_find_a_similarity_warp(stride):
    """The patch stride (services.ba.core.params.FlowParams.patch_stride; None: the preset's 3) changes what DIS
    computes, and at either the grid targets of a small rotation with zoom land on the true cell positions."""
    img = _texture(128, 160, seed=5)
    centre, angle, zoom = (79.5, 63.5), 2.0, 1.03
    warp = cv2.getRotationMatrix2D(centre, angle, zoom)  # x' = A x + b, in pixel-centre coordinates
    moved = cv2.warpAffine(img, warp, (160, 128), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    out = flow_targets(img, moved, FlowParams(patch_stride=stride))
    rows, cols = np.mgrid[0:16, 0:20]
    centres = np.stack([cols * 8 + 3.5, rows * 8 + 3.5], -1)  # each cell's centre in working pixels
    landed = centres @ warp[:, :2].T + warp[:, 2]
    want = (landed + 0.5) / 8 - 0.5  # docs/CONVENTIONS.md: pixels -> grid coordinates
    interior = (slice(3, -3), slice(3, -3))
    np.testing.assert_allclose(out.target[interior], want[interior], atol=0.06)
    other = flow_targets(img, moved, FlowParams(patch_stride=3 if stride == 4 else 4))
    assert np.abs(other.flow - out.flow).max() > 1e-3  # the setting reached DIS


def test_settings_carry_the_patch_stride_to_mapping_and_tracking(monkeypatch):
    from services.ba.settings import BaSettings

    monkeypatch.setenv("KMVIPE_BA_FLOW_PATCH_STRIDE", "3")
    cfg = BaSettings()
    assert cfg.flow_params().patch_stride == 3 and cfg.tracking_flow_params().patch_stride == 3
    assert BaSettings(flow_patch_stride=None).flow_params().patch_stride is None
    assert FlowParams().patch_stride is None


def test_flow_parameters_for_a_bare_pair_take_the_dense_patch_stride():
    from services.ba.settings import BaSettings

    params = BaSettings(flow_low_texture_patch_stride=1).flow_params()
    assert params.for_texture(params.low_texture_below) is params  # enough to see: the preset's patches
    assert params.for_texture(params.low_texture_below - 0.1).patch_stride == params.low_texture_patch_stride == 1
    assert FlowParams().for_texture(0.0).patch_stride == 1  # on by default (for keyframe edges: frames.py)
    assert FlowParams(low_texture_patch_stride=None).for_texture(0.0) == FlowParams(low_texture_patch_stride=None)


def test_the_dense_patch_rule_is_turned_off_from_the_environment(monkeypatch):
    from services.ba.settings import BaSettings

    monkeypatch.setenv("KMVIPE_BA_FLOW_LOW_TEXTURE_PATCH_STRIDE", "none")
    assert BaSettings().flow_params().low_texture_patch_stride is None
    monkeypatch.setenv("KMVIPE_BA_FLOW_LOW_TEXTURE_PATCH_STRIDE", "2")
    assert BaSettings().flow_params().low_texture_patch_stride == 2


@pytest.mark.parametrize("name, dense", [("rot1", False), ("low_texture", True)])
def test_keyframe_edges_of_bare_walls_are_flowed_with_dense_patches(name, dense):
    """The graph's edge targets are DIS's at the dense stride for a pair that shows too little (the synthetic
    bare wall, texture ~1) and at the preset's for a textured room (~12): the rule reaches the flows BA uses."""
    from services.common.image_texture import texture

    images = _two_views(name)
    params = FlowParams(low_texture_patch_stride=1)
    assert (min(map(texture, images)) < params.low_texture_below) == dense
    got = _graph_of(images, params).targets(0, 1).target.numpy()
    dense_targets = pair_targets(*images, FlowParams(patch_stride=1))[0].target
    preset_targets = pair_targets(*images, params)[0].target
    np.testing.assert_array_equal(got, dense_targets if dense else preset_targets)
    assert not np.array_equal(dense_targets, preset_targets)


def test_with_the_dense_patch_rule_off_no_keyframe_texture_is_measured():
    """With the rule off the graph's flows take the preset's patches and never pay for measuring the images."""
    images = _two_views("low_texture")
    off = FlowParams(low_texture_patch_stride=None)
    graph = _graph_of(images, off)
    got = graph.targets(0, 1).target.numpy()
    np.testing.assert_array_equal(got, pair_targets(*images, off)[0].target)
    assert graph._texture == {}


@pytest.mark.parametrize("name, bare", [("rot1", False), ("low_texture", True)])
def test_a_lossless_bare_pair_keeps_the_working_size_when_edge_flows_are_halved(name, bare):
    """``keyframe_flow_downscale`` 2 halves a lossless stream's edge flows; a bare pair keeps the working size (half
    the size leaves DIS half of what little a bare wall shows), so its targets are the dense-patch working-size
    ones. A textured pair's come from the halved images; a live stream's (a cheap preset) always do."""
    from dataclasses import replace

    images = _two_views(name)
    params = FlowParams()
    halves, at_half = _halved(images, params)
    for preset in (None, "ultrafast"):
        got = _graph_of(images, params, flow_downscale=2, flow_preset=preset).targets(0, 1).target.numpy()
        if preset is None and bare:
            want = pair_targets(*images, params.for_texture(0.0))[0].target
        else:
            half_params = at_half if preset is None else replace(at_half, preset=preset)
            want = pair_targets(*halves, half_params)[0].target
        np.testing.assert_array_equal(got, want)


def test_a_lossless_pair_with_little_parallax_keeps_the_working_size_when_edge_flows_are_halved():
    """With halved edge flows a pair whose poses predict under ``full_size_below_parallax`` working px of
    translational parallax (a camera that turned on the spot) keeps the working size: its depth and translation are
    in flow differences of a pixel or less. The same images with the second camera 0.1 units to the side (4 grid px of
    parallax at disparity 1) get the half-size targets; so does the pair with the rule off."""
    import torch

    images = _two_views("rot1")
    params = FlowParams()
    full = pair_targets(*images, params)[0].target
    halves, at_half = _halved(images, params)
    half = pair_targets(*halves, at_half)[0].target
    side = torch.eye(4, dtype=torch.float64)
    side[0, 3] = 0.1
    for second, below, want in ((None, 2.0, full), (side, 2.0, half), (None, 0.0, half)):
        graph = _graph_of(images, params, second, flow_downscale=2, full_size_below_parallax=below)
        np.testing.assert_array_equal(graph.targets(0, 1).target.numpy(), want)


def test_a_frames_flow_on_a_bare_wall_keeps_the_presets_patches():
    """Dense patches are for keyframe edges, which BA weighs against many others. A frame's pose is solved from its
    own flow alone, and over a bare person filling the view dense patches follow the person (the 10,000-frame
    orbit's frames 4150-4449: 0.048 m with them, 0.022 m without), so its flow keeps the preset's patches."""
    from dataclasses import replace

    import torch

    from services.ba.core.flow import flow_targets
    from services.ba.frontend.frames import FramePoses, FrameRecord
    from services.ba.frontend.graph import KeyframeGraph
    from services.ba.frontend.params import MotionParams
    from services.common.image_texture import texture

    keyframe, frame = _two_views("low_texture")
    params = FlowParams()  # the rule on, as by default, and the wall bare enough for it
    assert params.low_texture_patch_stride == 1 and texture(keyframe) < params.low_texture_below
    graph = KeyframeGraph(torch.tensor([40.0, 40.0, 15.5, 11.5], dtype=torch.float64), (24, 32), params,
                          torch.device("cpu"))
    graph.append(0, 0, keyframe, None, None, torch.eye(4, dtype=torch.float64), torch.ones(24, 32, dtype=torch.float64))
    small, at_half = _halved([keyframe, frame], params)
    frames = FramePoses(MotionParams())
    record = FrameRecord(4, 4, small[1])
    frames.add(record)
    got = frames._targets(graph, 0, record).target.numpy()
    np.testing.assert_array_equal(got, flow_targets(*small, replace(at_half, low_texture_patch_stride=None)).target)
    assert not np.array_equal(got, flow_targets(*small, replace(at_half, patch_stride=1)).target)
