"""Code conversion between PCA basis versions (services/common/pca_codes.py) against ground truth."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from services.common.pca_codes import code_map, convert_codes, convert_sums, identity_map
from services.features.core.pca import fit_pca, project, reconstruct

D, K = 48, 8


def _basis(seed: int, version: int):
    """A basis fitted (features core) on random low-rank data drawn around a seed-dependent subspace."""
    g = torch.Generator().manual_seed(seed)
    sub = torch.linalg.qr(torch.randn(D, 12, generator=g))[0]
    x = torch.randn(600, 12, generator=g) * torch.linspace(3, 1, 12) @ sub.T + torch.randn(D, generator=g)
    return fit_pca(x, K, "test", version)


def test_converted_codes_reconstruct_to_the_projection_of_the_source_reconstruction():
    a, b = _basis(1, 1), _basis(2, 2)
    z_a = np.random.default_rng(0).normal(size=(5, 7, K)) * 2
    f_a = reconstruct(a, z_a).astype(np.float64)
    v_b, mu_b = b.components.astype(np.float64), b.mean.astype(np.float64)
    projected = mu_b + ((f_a - mu_b) @ v_b.T) @ v_b  # orthogonal projection onto B's affine subspace
    z_b = convert_codes(z_a, code_map(a, b))
    assert z_b.shape == (5, 7, K) and z_b.dtype == np.float32
    np.testing.assert_allclose(mu_b + z_b.astype(np.float64) @ v_b, projected, atol=1e-4)
    # and it is exactly what B's own projection of A's reconstruction gives
    direct = project(b, torch.from_numpy(f_a.reshape(-1, D).T.reshape(D, 5, 7)).float()).astype(np.float32)
    np.testing.assert_allclose(z_b, direct, atol=2e-2)  # project() rounds to float16


def test_a_basis_to_itself_is_the_identity():
    a = _basis(3, 1)
    z = np.random.default_rng(1).normal(size=(100, K)).astype(np.float32)
    np.testing.assert_allclose(convert_codes(z, code_map(a, a)), z, atol=1e-5)
    assert identity_map(K).is_identity and not code_map(a, _basis(4, 2)).is_identity
    np.testing.assert_array_equal(convert_codes(z, identity_map(K)), z)


def test_torch_and_numpy_agree_and_keep_device_and_dtype():
    cmap = code_map(_basis(5, 1), _basis(6, 2))
    z = np.random.default_rng(2).normal(size=(4, 6, K)).astype(np.float16)
    t = convert_codes(torch.from_numpy(z), cmap)
    assert t.dtype == torch.float32 and t.device.type == "cpu"
    np.testing.assert_allclose(t.numpy(), convert_codes(z, cmap), atol=1e-6)


def test_weighted_sums_map_like_weighted_means():
    cmap = code_map(_basis(7, 1), _basis(8, 2))
    rng = np.random.default_rng(3)
    z, w = rng.normal(size=(30, K)), rng.uniform(0.1, 2.0, 30)
    sums = convert_sums((w[:, None] * z).sum(0, keepdims=True), np.array([w.sum()]), cmap)
    expect = (w[:, None] * convert_codes(z, cmap).astype(np.float64)).sum(0)
    np.testing.assert_allclose(sums[0], expect, rtol=1e-5, atol=1e-5)


def test_going_through_an_intermediate_basis_loses_what_the_direct_map_keeps():
    """Why consumers convert from each keyframe's own version: A → B → C projects twice."""
    a, b, c = _basis(9, 1), _basis(10, 2), _basis(11, 3)
    z = np.random.default_rng(4).normal(size=(200, K)) * 3
    direct = convert_codes(z, code_map(a, c))
    chained = convert_codes(convert_codes(z, code_map(a, b)), code_map(b, c))
    assert np.abs(direct - chained).max() > 0.1


def test_mismatched_shapes_are_refused():
    a = _basis(12, 1)
    with pytest.raises(ValueError):
        code_map(a, SimpleNamespace(mean=np.zeros(D - 1), components=np.zeros((K, D - 1))))  # another D
    with pytest.raises(ValueError):
        code_map(a, SimpleNamespace(mean=np.zeros(D), components=np.zeros((D, K))))  # components transposed
    with pytest.raises(ValueError):
        convert_codes(np.zeros((3, K + 1)), code_map(a, a))
