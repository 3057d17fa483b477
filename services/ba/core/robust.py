"""Barron's general robust loss and the ARK (adaptive robust kernel) shape map.

Barron, "A General and Adaptive Robust Loss Function", CVPR 2019, eq. (1), with ``z = (x/c)^2`` and
``b = |alpha - 2|``::

    rho(x, alpha, c) = b/alpha * ((z/b + 1)^(alpha/2) - 1)
    psi(x)           = d rho / d x = x / c^2 * (z/b + 1)^(alpha/2 - 1)
    weight(x)        = psi(x) / x  = 1 / c^2 * (z/b + 1)^(alpha/2 - 1)        (the IRLS weight)

Limits (used exactly at the special values): alpha = 2 -> z/2 (L2); alpha = 0 -> log(z/2 + 1) (Cauchy);
alpha = -inf -> 1 - exp(-z/2) (Welsch); alpha = 1 is the general formula (pseudo-Huber sqrt(z+1) - 1).
Near the special values the general formula is evaluated as ``b/alpha * expm1(alpha/2 * log1p(z/b))`` with
``alpha`` and ``b`` kept at least ``EPS`` away from 0, so it is continuous and differentiable through them.

All functions are element-wise and broadcast ``x``, ``alpha``, ``c`` (any shape, float32 or float64).
"""
from __future__ import annotations

import math

import torch

# Smallest |alpha| and |alpha - 2| used in the general formula; the relative error this introduces near the
# special values is O(EPS) (same guard as Barron's reference implementation).
EPS = 1e-9


def _parts(x: torch.Tensor, alpha: torch.Tensor, scale: torch.Tensor):
    x, alpha, scale = torch.broadcast_tensors(torch.as_tensor(x), torch.as_tensor(alpha, dtype=x.dtype),
                                              torch.as_tensor(scale, dtype=x.dtype))
    z = (x / scale) ** 2
    b_safe = (alpha - 2).abs().clamp_min(EPS)
    sign = torch.where(alpha >= 0, torch.ones_like(alpha), -torch.ones_like(alpha))
    a_safe = sign * alpha.abs().clamp_min(EPS)
    finite = torch.isfinite(alpha)
    # Very negative finite alpha: b -> inf and log1p(z/b) -> z/b, fine; -inf handled by the Welsch branch.
    a_fin = torch.where(finite, a_safe, -torch.ones_like(alpha))
    b_fin = torch.where(finite, b_safe, 3 * torch.ones_like(alpha))
    return x, alpha, scale, z, a_fin, b_fin, finite


def rho(x: torch.Tensor, alpha, scale) -> torch.Tensor:
    """Barron loss ``rho(x, alpha, c)`` (dimensionless, ``rho(0) = 0``, ``rho ~ x^2 / (2 c^2)`` near 0)."""
    x, alpha, scale, z, a, b, finite = _parts(x, alpha, scale)
    general = b / a * torch.expm1(0.5 * a * torch.log1p(z / b))
    out = torch.where(alpha == 2, 0.5 * z, general)
    out = torch.where(alpha == 0, torch.log1p(0.5 * z), out)
    return torch.where(finite, out, -torch.expm1(-0.5 * z))


def weight(x: torch.Tensor, alpha, scale) -> torch.Tensor:
    """IRLS weight ``psi(x)/x`` (units 1/c^2; ``1/c^2`` at ``x = 0``); finite at ``x = 0``."""
    x, alpha, scale, z, a, b, finite = _parts(x, alpha, scale)
    inv_c2 = 1 / scale**2
    general = inv_c2 * torch.exp((0.5 * a - 1) * torch.log1p(z / b))
    out = torch.where(alpha == 2, inv_c2.expand_as(z), general)
    out = torch.where(alpha == 0, inv_c2 / (0.5 * z + 1), out)
    return torch.where(finite, out, inv_c2 * torch.exp(-0.5 * z))


def psi(x: torch.Tensor, alpha, scale) -> torch.Tensor:
    """Influence function ``d rho / d x`` (units 1/[x])."""
    return torch.as_tensor(x) * weight(x, alpha, scale)


def ark_alpha(cosine: torch.Tensor, alpha_static: float, alpha_dynamic: float, kappa: float,
              tau: float) -> torch.Tensor:
    """Per-pixel shape ``alpha(u) = (a_dyn - a_static) / (1 + exp((cs(u) - kappa)/tau)) + a_static``.

    Args:
        cosine: ``(...)`` cosine similarity in [-1, 1] of the codes of ``u`` and of its reprojection.
        alpha_static: shape for consistent (static) pixels, e.g. 2 (L2).
        alpha_dynamic: shape for inconsistent (dynamic) pixels, <= 0 (Cauchy or heavier).
        kappa: cosine similarity at the sigmoid's midpoint.
        tau: sigmoid temperature (> 0); smaller = sharper switch.
    Returns:
        ``(...)`` alpha, same dtype as ``cosine``.
    """
    if not tau > 0 or not math.isfinite(tau):
        raise ValueError(f"tau must be a positive finite number, got {tau}")
    return alpha_static + (alpha_dynamic - alpha_static) * torch.sigmoid(-(cosine - kappa) / tau)
