"""PCA codes: known low-rank answer, round trip, frozen fit, keyframe queue; pyramid blending."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from services.features.core.pca import PcaParams, fit_pca, project, reconstruct, retained_variance
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

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        self.calls.append(tuple(x.shape[2:]))
        h, w = x.shape[2] // 14, x.shape[3] // 14
        out = torch.zeros(1, 2, h, w)
        out[:, 0, :, : w // 2] = 1.0
        out[:, 1, :, w // 2 :] = 1.0
        return out


def test_pyramid_sizes_weights_and_blend():
    bb = _PositionBackbone()
    params = PyramidParams(scales=(2.0, 1.0, 0.5))
    res = multiscale_features(torch.zeros(1, 3, 112, 224), bb, params)
    assert bb.calls == [scaled_size(112, 224, s, 14) for s in params.scales]
    assert all(h % 14 == 0 and w % 14 == 0 for h, w in bb.calls)
    assert scale_weights(params.scales) == pytest.approx([2 / 3.5, 1 / 3.5, 0.5 / 3.5])
    f = res.features
    assert f.shape == (2, 14, 28)
    assert torch.allclose(f.norm(dim=0), torch.ones(14, 28), atol=1e-5)
    assert f[0, :, 0].min() > 0.99 and f[1, :, -1].min() > 0.99  # far left / far right cells
    assert set(res.seconds_per_scale) == set(params.scales)
