"""The camera model BA refines: which intrinsics are free, where a step may move them, and the principal point's
prior.

Intrinsics are ``(fx, fy, cx, cy)`` of the BA grid. The focal is one variable, fx, with fy keeping its ratio to fx
(the working resize may scale x and y differently, so fy/fx is known, not 1). With
``BAParams.optimise_principal_point`` the principal point ``(cx, cy)`` is two more, pulled to a first guess by a
Gaussian prior and held inside a range about the grid's centre. In the camera system they follow the poses: index
``6 N`` is fx, ``6 N + 1`` and ``6 N + 2`` are cx and cy.
"""
from __future__ import annotations

from typing import NamedTuple

import torch

from services.ba.core.params import BAParams


def estimates_principal_point(params: BAParams) -> bool:
    """Whether (cx, cy) are variables: only where the focal is (a principal point alone is never refined)."""
    return params.optimise_focal and params.optimise_principal_point


def count(params: BAParams) -> int:
    """Intrinsic columns of the camera system: the focal alone (1), or the focal and the principal point (3)."""
    return 3 if estimates_principal_point(params) else 1


def free_camera_indices(n_kf: int, params: BAParams, device) -> torch.Tensor:
    """Indices of the camera system's variables a solve moves: the poses past the gauge's, then the free
    intrinsics."""
    free = torch.arange(6 * min(params.fixed_poses, n_kf), 6 * n_kf, device=device)
    if params.optimise_focal:
        free = torch.cat([free, 6 * n_kf + torch.arange(count(params), device=device)])
    return free


class PrincipalPrior(NamedTuple):
    """The principal point's Gaussian prior at one state, in the camera system's terms."""

    indices: torch.Tensor  # (2,) its columns in the camera system (6 N + 1, 6 N + 2)
    diagonal: torch.Tensor  # (2,) its Hessian
    gradient: torch.Tensor  # (2,) minus its energy's gradient
    energy: float


def principal_prior(intrinsics: torch.Tensor, guess: torch.Tensor, params: BAParams,
                    n_kf: int = 0) -> PrincipalPrior | None:
    """The prior pulling (cx, cy) to ``guess`` at ``intrinsics`` in a camera system of ``n_kf`` keyframes, or None
    when the principal point is held."""
    if not estimates_principal_point(params):
        return None
    diff = intrinsics[2:] - guess
    weight = 1.0 / params.principal_point_sigma**2
    return PrincipalPrior(6 * n_kf + torch.tensor([1, 2], device=diff.device), torch.full_like(diff, weight),
                          -weight * diff,
                          float(0.5 * weight * (diff**2).sum()))


def principal_energy(intrinsics: torch.Tensor, guess: torch.Tensor, params: BAParams) -> float:
    prior = principal_prior(intrinsics, guess, params)
    return 0.0 if prior is None else prior.energy


def apply_step(intrinsics: torch.Tensor, focal_step: torch.Tensor, principal_step: torch.Tensor,
               grid_hw: tuple[int, int], params: BAParams,
               focal_bounds: tuple[float, float] | None = None) -> torch.Tensor:
    """``intrinsics`` moved by a step in fx (fy keeping fy/fx) and in (cx, cy), each projected onto its bounds:
    the focal onto ``focal_bounds``, the principal point onto ``BAParams.principal_point_range`` about the grid's
    centre. A step pushed against a bound still moves everything else (a result is never thrown away for it)."""
    intr = intrinsics.clone()
    fx = intr[0] + focal_step
    if focal_bounds is not None:
        fx = fx.clamp(*focal_bounds)
    intr[:2] = intr[:2] * (fx / intr[0])
    if estimates_principal_point(params):
        h, w = grid_hw
        size = intr.new_tensor([w, h])
        low = (size - 1) / 2 - params.principal_point_range * size
        intr[2:] = torch.minimum(torch.maximum(intr[2:] + principal_step.to(intr.dtype), low), size - 1 - low)
    return intr
