"""Barron's general robust loss and the ARK (adaptive robust kernel) shape maps (ours and KM-ViPE's reference).

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
from typing import NamedTuple

import torch

# Smallest |alpha| and |alpha - 2| used in the general formula; the relative error this introduces near the
# special values is O(EPS) (same guard as Barron's reference implementation).
EPS = 1e-9


class Kernel(NamedTuple):
    """Constants of ``rho``/``weight`` for one shape map ``alpha``, formed once and reused: IRLS evaluates the
    same frozen shapes many times per iteration, and forming them costs more than the evaluation itself."""

    inv_b: torch.Tensor  # 1 / b, b = |alpha - 2| kept >= EPS
    coef: torch.Tensor  # b / alpha (alpha kept >= EPS away from 0)
    half_a: torch.Tensor  # alpha / 2
    w_exp: torch.Tensor  # alpha / 2 - 1
    l2: torch.Tensor | None  # bool where alpha == 2 exactly (None: nowhere)
    cauchy: torch.Tensor | None  # bool where alpha == 0 exactly
    welsch: torch.Tensor | None  # bool where alpha is -inf


def kernel(alpha, dtype: torch.dtype = torch.float64, device=None) -> Kernel:
    """:class:`Kernel` of ``alpha`` (a number or a tensor of any shape)."""
    alpha = torch.as_tensor(alpha, dtype=dtype, device=device)
    finite = torch.isfinite(alpha)
    b = (alpha - 2).abs().clamp_min(EPS)
    sign = torch.where(alpha >= 0, torch.ones_like(alpha), -torch.ones_like(alpha))
    # very negative finite alpha: b -> inf and log1p(z/b) -> z/b, fine; -inf is the Welsch branch
    a = torch.where(finite, sign * alpha.abs().clamp_min(EPS), -torch.ones_like(alpha))
    b = torch.where(finite, b, 3 * torch.ones_like(alpha))

    def where(mask: torch.Tensor) -> torch.Tensor | None:
        return mask if bool(mask.any()) else None

    return Kernel(1 / b, b / a, 0.5 * a, 0.5 * a - 1, where(alpha == 2), where(alpha == 0), where(~finite))


def _as_kernel(alpha, x: torch.Tensor) -> Kernel:
    return alpha if isinstance(alpha, Kernel) else kernel(alpha, x.dtype, x.device)


def rho(x: torch.Tensor, alpha, scale) -> torch.Tensor:
    """Barron loss ``rho(x, alpha, c)`` (dimensionless, ``rho(0) = 0``, ``rho ~ x^2 / (2 c^2)`` near 0);
    ``alpha`` is a number, a tensor or a :class:`Kernel`."""
    x = torch.as_tensor(x)
    k = _as_kernel(alpha, x)
    z = (x / scale) ** 2
    out = k.coef * torch.expm1(k.half_a * torch.log1p(z * k.inv_b))
    if k.l2 is not None:
        out = torch.where(k.l2, 0.5 * z, out)
    if k.cauchy is not None:
        out = torch.where(k.cauchy, torch.log1p(0.5 * z), out)
    if k.welsch is not None:
        out = torch.where(k.welsch, -torch.expm1(-0.5 * z), out)
    return out


def weight(x: torch.Tensor, alpha, scale) -> torch.Tensor:
    """IRLS weight ``psi(x)/x`` (units 1/c^2; ``1/c^2`` at ``x = 0``); finite at ``x = 0``; ``alpha`` is a
    number, a tensor or a :class:`Kernel`."""
    x = torch.as_tensor(x)
    k = _as_kernel(alpha, x)
    z = (x / scale) ** 2
    inv_c2 = 1 / torch.as_tensor(scale, dtype=x.dtype, device=x.device) ** 2
    out = inv_c2 * torch.exp(k.w_exp * torch.log1p(z * k.inv_b))
    if k.l2 is not None:
        out = torch.where(k.l2, inv_c2.expand_as(out), out)
    if k.cauchy is not None:
        out = torch.where(k.cauchy, inv_c2 / (0.5 * z + 1), out)
    if k.welsch is not None:
        out = torch.where(k.welsch, inv_c2 * torch.exp(-0.5 * z), out)
    return out


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


def ark_alpha_paper(cosine: torch.Tensor, alpha_low: float = -10.0, alpha_high: float = 2.0, floor: float = 0.4,
                    mid: float = 0.5, tau: float = 0.1) -> torch.Tensor:
    """KM-ViPE's reference shape map (be2rlab/km-vipe, ``vipe/slam/ba/terms.py``, ``calculate_alpha``)::

        alpha(cs) = alpha_low                                                       cs <  floor
                  = alpha_low + (alpha_high - alpha_low) * sigmoid((x - mid) / tau)  cs >= floor,
        x = clamp((cs - floor) / (1 - floor), 0, 1)

    With the defaults: -10 below cs = 0.4, a logistic ramp above it with midpoint cs = 0.7 (alpha = -4) that
    reaches 1.92 at cs = 1; the ramp starts at -9.92, so the map jumps by 0.08 at the floor (kept: it is the
    reference's). Monotone non-decreasing in cs.

    Args:
        cosine: ``(...)`` cosine similarity in [-1, 1] (the reference compares raw, un-centred DINO features).
    Returns:
        ``(...)`` alpha, same dtype as ``cosine``.
    """
    if not tau > 0 or not floor < 1:
        raise ValueError(f"tau must be > 0 and floor < 1, got tau={tau}, floor={floor}")
    x = ((cosine - floor) / (1 - floor)).clamp(0, 1)
    ramp = alpha_low + (alpha_high - alpha_low) * torch.sigmoid((x - mid) / tau)
    return torch.where(cosine < floor, torch.full_like(ramp, alpha_low), ramp)


def ark_shape(cosine: torch.Tensor, params) -> torch.Tensor:
    """Per-pixel shape of the ARK mode ``params.ark_mode`` (a :class:`services.ba.core.params.RobustParams`):
    "centred" is :func:`ark_alpha`, "paper" is :func:`ark_alpha_paper`."""
    if params.ark_mode == "paper":
        return ark_alpha_paper(cosine, params.paper_alpha_low, params.paper_alpha_high, params.paper_floor,
                               params.paper_mid, params.paper_tau)
    if params.ark_mode == "centred":
        return ark_alpha(cosine, params.alpha_static, params.alpha_dynamic, params.kappa, params.tau)
    raise ValueError(f"ark_mode must be 'centred' or 'paper', got {params.ark_mode!r}")
