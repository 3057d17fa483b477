"""FeaturesCore end to end on synthetic frames with tiny registry models (no network, fast)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

pytest.importorskip("transformers")
synth = pytest.importorskip("services.synth")

from services.common.models import ModelStore  # noqa: E402
from services.common.models.backbones import normalise_rgb  # noqa: E402
from services.common.models.loaders import load_backbone, load_depth_model  # noqa: E402
from services.common.models.tiny import TINY_DIM, write_tiny_model  # noqa: E402
from services.features.core.geometry import Intrinsics  # noqa: E402
from services.features.core.pca import PcaParams  # noqa: E402
from services.features.core.pipeline import CodeQueue, FeaturesCore, FeaturesParams, KeyframeOut, LiteOut  # noqa: E402
from services.features.core.pyramid import PyramidParams  # noqa: E402


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    root = tmp_path_factory.mktemp("models")
    write_tiny_model("dinov2-vitb14-reg", root)
    write_tiny_model("depth-anything-v2-metric-indoor-small", root)
    return ModelStore(root, use_hf_cache=False)


def _params() -> FeaturesParams:
    return FeaturesParams(pyramid=PyramidParams(scales=(1.0, 0.5)), pca=PcaParams(n_components=8, fit_keyframes=2))


# CUDA where there is one: the first run on a GPU machine died in the PCA fit (a CUDA tensor to numpy)
@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(
    not torch.cuda.is_available(), reason="no CUDA device here (bench/gpu_check.sh runs it on a lent GPU)"))])
def test_stream_of_frames_gives_keyframes_lites_codes_and_sensor_disparity(store, device):
    cfg = synth.SynthConfig(n_frames=30, camera="orbit", person=False, moved_chair=False)
    world = synth.SynthWorld(cfg)
    core = FeaturesCore(_params(), load_backbone("dinov2-vitb14-reg", store, device, half=False), normalise_rgb)
    queue = CodeQueue(core.params.pca, "tiny")
    outs, coded, bases = [], [], []
    for i in range(cfg.n_frames):
        f = world.render(i)
        out = core.process(i, f.rgb, hint=Intrinsics(*f.intrinsics), sensor_depth=f.depth)
        if isinstance(out, KeyframeOut):
            assert out.features is None  # geometry leaves first; semantics are a step of their own
            out = core.describe(out)
            basis, ready = queue.add(out)
            bases += [basis] if basis else []
            coded += ready
        outs.append(out)
    last = core.promote_last()
    kfs = [o for o in outs if isinstance(o, KeyframeOut)]
    lites = [o for o in outs if isinstance(o, LiteOut)]
    assert outs[0].seq == 0 and isinstance(outs[0], KeyframeOut)
    assert len(kfs) >= 2 and len(lites) >= 5
    assert (last is None) == isinstance(outs[-1], KeyframeOut)
    kf = kfs[0]
    H, W = kf.image.shape[:2]
    assert (H, W) == (384, 512) and kf.features.shape == (TINY_DIM, H // 8, W // 8)
    # intrinsics follow the hint through the (identity here) resize
    assert np.allclose(kf.intrinsics, world.render(0).intrinsics)
    # sensor depth → disparity on the grid: mean inverse depth of each 8×8 cell
    d0 = world.render(0).depth
    expected = (1.0 / d0).reshape(H // 8, 8, W // 8, 8).mean(axis=(1, 3))
    assert np.allclose(kf.disparity, expected, rtol=1e-4)
    # the PCA basis appears once, after fit_keyframes keyframes; codes come in keyframe order
    assert len(bases) == 1 and bases[0].version == 1
    assert [k.seq for k, _ in coded] == [k.seq for k in kfs]
    assert all(c.shape == (H // 8, W // 8, 8) and c.dtype == np.float16 for _, c in coded)
    lite = lites[0]
    assert lite.grey.shape == (192, 256) and lite.grey.dtype == np.uint8
    assert np.allclose(lite.intrinsics, Intrinsics(*world.render(0).intrinsics).scaled(0.5, 0.5))
    assert {"resize", "flow", "scale_1", "scale_0.5", "depth"} <= set(kf.seconds)


def test_fov_prior_and_refined_intrinsics(store):
    core = FeaturesCore(_params(), load_backbone("dinov2-vitb14-reg", store, "cpu"), normalise_rgb)
    img = np.random.default_rng(0).integers(0, 255, (370, 1226), dtype=np.uint8)  # grey, KITTI-sized
    kf = core.process(0, img)
    assert kf.image.shape == (240, 808, 3)
    f = 0.5 * 1226 / np.tan(np.radians(30.0)) * 808 / 1226
    assert kf.intrinsics.fx == pytest.approx(f)
    core.intrinsics.refine(Intrinsics(700.0, 700.0, 400.0, 120.0), width=808, height=240)
    k = core.intrinsics.for_original(370, 1226, hint=Intrinsics(1.0, 1.0, 1.0, 1.0))
    assert k.fx == pytest.approx(700.0 * 1226 / 808)  # ba's refinement wins over the hint


def test_depth_model_prior_is_positive_disparity(store):
    depth = load_depth_model("depth-anything-v2-metric-indoor-small", store, "cpu")
    core = FeaturesCore(_params(), load_backbone("dinov2-vitb14-reg", store, "cpu"), normalise_rgb, depth)
    frame = synth.SynthWorld(synth.SynthConfig(n_frames=2)).render(0)
    kf = core.process(0, frame.rgb)
    assert kf.disparity.shape == (48, 64) and kf.disparity.dtype == np.float32
    assert np.all(kf.disparity >= 0.0)
