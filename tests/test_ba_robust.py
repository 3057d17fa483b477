"""Barron's general loss: rho/psi/weight vs autograd and closed forms, special cases, ARK alpha map."""
from __future__ import annotations

import math

import pytest
import torch

from services.ba.core import robust

X = torch.linspace(-7.0, 7.0, 141, dtype=torch.float64)
SCALE = 0.8


def _direct(x, alpha, c):
    """Barron eq. (1) written literally (valid away from alpha in {0, 2})."""
    b = abs(alpha - 2)
    return b / alpha * (((x / c) ** 2 / b + 1) ** (alpha / 2) - 1)


@pytest.mark.parametrize("alpha", [2.0, 1.0, 0.0, -2.0, -10.0, -math.inf,
                                   2 + 1e-7, 2 - 1e-7, 1e-7, -1e-7, 0.5, 3.0, -1e6])
def test_psi_and_weight_match_autograd(alpha):
    x = X.clone().requires_grad_(True)
    loss = robust.rho(x, alpha, SCALE)
    (grad,) = torch.autograd.grad(loss.sum(), x)
    torch.testing.assert_close(robust.psi(X, alpha, SCALE), grad, rtol=1e-6, atol=1e-12)
    nonzero = X.abs() > 1e-3
    torch.testing.assert_close(robust.weight(X, alpha, SCALE)[nonzero], (grad / X)[nonzero], rtol=1e-6, atol=1e-12)


@pytest.mark.parametrize("alpha", [1.0, -2.0, -10.0, 0.5, 3.0])
def test_rho_matches_literal_formula(alpha):
    torch.testing.assert_close(robust.rho(X, alpha, SCALE), _direct(X, alpha, SCALE), rtol=1e-10, atol=1e-14)


def test_special_cases_closed_forms():
    z = (X / SCALE) ** 2
    torch.testing.assert_close(robust.rho(X, 2.0, SCALE), z / 2)
    torch.testing.assert_close(robust.rho(X, 0.0, SCALE), torch.log(z / 2 + 1))
    torch.testing.assert_close(robust.rho(X, -math.inf, SCALE), 1 - torch.exp(-z / 2))
    torch.testing.assert_close(robust.rho(X, 1.0, SCALE), torch.sqrt(z + 1) - 1)
    torch.testing.assert_close(robust.weight(X, 2.0, SCALE), torch.full_like(X, 1 / SCALE**2))
    torch.testing.assert_close(robust.weight(X, 0.0, SCALE), 1 / SCALE**2 / (z / 2 + 1))


@pytest.mark.parametrize("special,offsets", [(2.0, [1e-4, 1e-6, 1e-8]), (0.0, [1e-4, 1e-6, 1e-8])])
def test_continuous_through_special_values(special, offsets):
    at = robust.rho(X, special, SCALE)
    w_at = robust.weight(X, special, SCALE)
    for off in offsets:
        for a in (special - off, special + off):
            # the deviation is first order in the offset
            torch.testing.assert_close(robust.rho(X, a, SCALE), at, rtol=50 * off, atol=1e-12)
            torch.testing.assert_close(robust.weight(X, a, SCALE), w_at, rtol=50 * off, atol=1e-12)


def test_welsch_is_limit_of_very_negative_alpha():
    torch.testing.assert_close(robust.rho(X, -1e9, SCALE), robust.rho(X, -math.inf, SCALE), rtol=1e-6, atol=1e-9)
    torch.testing.assert_close(robust.weight(X, -1e9, SCALE), robust.weight(X, -math.inf, SCALE),
                               rtol=1e-6, atol=1e-9)


def test_per_element_alpha_broadcasts_and_is_finite():
    alpha = torch.tensor([2.0, 1.0, 0.0, -2.0, -10.0, -math.inf], dtype=torch.float64)[:, None]
    x = X[None, :].expand(6, -1).clone().requires_grad_(True)
    loss = robust.rho(x, alpha, SCALE)
    assert loss.shape == (6, 141)
    (grad,) = torch.autograd.grad(loss.sum(), x)
    assert torch.isfinite(grad).all()
    torch.testing.assert_close(robust.psi(X[None], alpha, SCALE), grad, rtol=1e-6, atol=1e-12)
    # weight at 0 is 1/c^2 for every shape; heavier tails (smaller alpha) down-weight outliers more
    w = robust.weight(torch.tensor([0.0, 5.0], dtype=torch.float64)[None], alpha, SCALE)
    torch.testing.assert_close(w[:, 0], torch.full((6,), 1 / SCALE**2, dtype=torch.float64))
    assert (w[1:, 1] < w[:-1, 1]).all()


def test_ark_alpha_map():
    cs = torch.tensor([-1.0, 0.0, 0.5, 0.7, 0.9, 1.0], dtype=torch.float64)
    alpha = robust.ark_alpha(cs, alpha_static=2.0, alpha_dynamic=-2.0, kappa=0.5, tau=0.05)
    expected = (-2.0 - 2.0) / (1 + torch.exp((cs - 0.5) / 0.05)) + 2.0
    torch.testing.assert_close(alpha, expected)
    assert alpha[2] == pytest.approx(0.0)  # midpoint at cs = kappa
    assert alpha[-1] == pytest.approx(2.0, abs=1e-3) and alpha[0] == pytest.approx(-2.0, abs=1e-3)
    with pytest.raises(ValueError):
        robust.ark_alpha(cs, 2.0, -2.0, 0.5, 0.0)
