"""KM-ViPE's reference ARK shape map (RobustParams.ark_mode="paper"): known answers, shape, Barron at its alphas,
and the un-centred codes whose cosine is the raw feature cosine the reference thresholds."""
from __future__ import annotations

import math

import pytest
import torch

from services.ba.core import embedding, robust
from services.ba.core.params import RobustParams


def _reference(cs: float) -> float:
    """The reference's calculate_alpha written out for one value (alpha_min -10, alpha_max 2)."""
    if cs < 0.4:
        return -10.0
    x = min(max((cs - 0.4) / 0.6, 0.0), 1.0)
    return 12.0 / (1 + math.exp(-(x - 0.5) / 0.1)) - 10.0


@pytest.mark.parametrize("cs", [-1.0, -0.3, 0.0, 0.39, 0.4, 0.45, 0.55, 0.7, 0.85, 0.95, 1.0])
def test_paper_alpha_known_answers(cs):
    got = robust.ark_alpha_paper(torch.tensor(cs, dtype=torch.float64))
    assert float(got) == pytest.approx(_reference(cs), abs=1e-12)


def test_paper_alpha_shape():
    cs = torch.linspace(-1, 1, 2001, dtype=torch.float64)
    alpha = robust.ark_alpha_paper(cs)
    assert (alpha[cs < 0.4] == -10).all()
    assert (alpha.diff() >= 0).all()  # monotone
    assert float(robust.ark_alpha_paper(torch.tensor(0.7))) == pytest.approx(-4.0)  # ramp midpoint
    top = float(robust.ark_alpha_paper(torch.tensor(1.0)))
    assert 1.9 < top < 2.0  # L2-like, never above 2
    # the reference's ramp starts at -9.92: a small jump at the floor, kept for fidelity
    assert float(robust.ark_alpha_paper(torch.tensor(0.4, dtype=torch.float64))) == pytest.approx(
        -10 + 12 / (1 + math.exp(5)))


def test_ark_shape_dispatch():
    cs = torch.linspace(-1, 1, 11, dtype=torch.float64)
    centred, paper = RobustParams(), RobustParams(ark_mode="paper")
    torch.testing.assert_close(robust.ark_shape(cs, centred), robust.ark_alpha(cs, 2.0, -2.0, 0.5, 0.05))
    torch.testing.assert_close(robust.ark_shape(cs, paper), robust.ark_alpha_paper(cs))


@pytest.mark.parametrize("kwargs", [{"ark_mode": "kmvipe"}, {"paper_floor": 1.0}, {"paper_tau": 0.0},
                                    {"tau": -1.0}, {"paper_alpha_low": 3.0}])
def test_robust_params_validation(kwargs):
    with pytest.raises(ValueError):
        RobustParams(**kwargs)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_barron_at_paper_alphas_matches_autograd(dtype):
    """Per-element alphas from the paper map (down to -10) through rho/psi/weight: finite, psi = d rho/dx."""
    gen = torch.Generator().manual_seed(0)
    cs = torch.rand(4000, generator=gen, dtype=torch.float64) * 2 - 1
    x = (torch.randn(4000, generator=gen, dtype=torch.float64) * 30).to(dtype)  # up to ~100 c: far tails
    alpha = robust.ark_alpha_paper(cs).to(dtype)
    kern = robust.kernel(alpha, dtype)
    scale = 0.5
    xr = x.clone().requires_grad_(True)
    loss = robust.rho(xr, kern, scale)
    (grad,) = torch.autograd.grad(loss.sum(), xr)
    w = robust.weight(x, kern, scale)
    assert torch.isfinite(loss).all() and torch.isfinite(w).all() and (w >= 0).all()
    tol = {"rtol": 1e-9, "atol": 1e-12} if dtype == torch.float64 else {"rtol": 1e-4, "atol": 1e-6}
    torch.testing.assert_close(robust.psi(x, kern, scale), grad, **tol)
    # alpha = -10 is bounded: rho < b/|alpha| = 1.2 however large the residual
    assert float(loss.detach()[alpha == -10].max()) <= 1.2 + 1e-6


def test_uncentred_codes_give_raw_feature_cosine():
    gen = torch.Generator().manual_seed(1)
    d, k = 48, 8
    q, _ = torch.linalg.qr(torch.randn(d, k, generator=gen, dtype=torch.float64))
    v = q.T  # (K, D) orthonormal rows
    mu = torch.randn(d, generator=gen, dtype=torch.float64) * 2
    z = torch.randn(2, 5, k, generator=gen, dtype=torch.float64)
    f = mu + z @ v  # the reconstructions
    raw = torch.nn.functional.cosine_similarity(f[0], f[1], dim=-1)
    u = embedding.uncentred_codes(z, mu, v)
    assert u.shape == (2, 5, k + 1)
    torch.testing.assert_close(torch.nn.functional.cosine_similarity(u[0], u[1], dim=-1), raw)
    centred = torch.nn.functional.cosine_similarity(z[0], z[1], dim=-1)
    assert (raw - centred).abs().max() > 0.1  # the two cosines differ: the mode choice matters
    with pytest.raises(ValueError):
        embedding.uncentred_codes(z, mu[:-1], v)


def test_ba_uses_the_mode_it_is_given():
    """run_ba weighs the flow with the configured ARK map: the same window and codes give a different energy."""
    import dataclasses

    from services.ba.core import ba, synthetic
    from services.ba.core.params import BAParams

    win = synthetic.make_window(n=4, h=12, w=16, seed=1, surface="room")
    codes = torch.randn(4, 12, 16, 8, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    problem = win.problem._replace(codes=codes)
    start = ba.BAState(synthetic.perturb_poses(win.truth.poses, 0.02, 1.0, torch.Generator().manual_seed(2)),
                       win.truth.disparity.clone(), win.truth.intrinsics.clone())
    base = BAParams(iterations=1, compute_dtype="float64")
    centred = ba.run_ba(start, problem, base)
    paper = ba.run_ba(start, problem, dataclasses.replace(base, robust=RobustParams(ark_mode="paper")))
    assert centred.costs[0] != pytest.approx(paper.costs[0], rel=1e-6)
