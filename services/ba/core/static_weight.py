"""How likely each keyframe pixel is to be static, from the evidence of a BA's edges: what the map leaves out as
moving (people, moved objects)."""
from __future__ import annotations

import torch

from services.ba.core import robust
from services.ba.core.ark import ArkCosine
from services.ba.core.params import RobustParams


def static_weight(flow_norm: torch.Tensor, flow_w: torch.Tensor, ii: torch.Tensor, n: int, rob: RobustParams,
                  ark: ArkCosine | None = None) -> torch.Tensor:
    """(N, P) probability that each keyframe pixel is static, from the evidence of all its out-edges: the edges'
    flow residual norms ``flow_norm`` (E, P) and weights ``flow_w`` (E, P, confidence x validity), source
    keyframes ``ii`` (E,), and with codes the ARK cosine at the reprojections ``ark``.

    With codes (ARK): the ARK sigmoid of the confidence-weighted mean cosine similarity over the edges,
    ``sigmoid((mean cs - kappa) / tau)`` (summing the per-edge log-odds ``(cs - kappa)/tau``: one view where the
    pixel is occluded or lands on a label border does not outvote the others), times the mean flow weight the
    dynamic kernel gives the pixel, ``c^2 psi_{alpha_dyn}(r)/r`` (a rigidly moving object whose codes still
    agree, e.g. the inside of a large moved object, shows up only in its flow). Without codes: the mean
    robust weight of the fixed kernel. 1 (no evidence of motion) where no edge sees the pixel.
    """
    votes = flow_w
    if ark is not None:
        votes = votes * ark.valid
        weight = rob.scale**2 * robust.weight(flow_norm, rob.alpha_dynamic, rob.scale)
    else:
        weight = rob.scale**2 * robust.weight(flow_norm, rob.fixed_alpha, rob.scale)
    total = torch.zeros(n, votes.shape[1], dtype=votes.dtype, device=votes.device).index_add_(0, ii, votes)
    denom = total.clamp_min(torch.finfo(votes.dtype).tiny)

    def mean(values: torch.Tensor) -> torch.Tensor:
        return torch.zeros_like(total).index_add_(0, ii, votes * values) / denom

    static = mean(weight)
    if ark is not None:
        static = static * torch.sigmoid((mean(ark.cosine) - rob.kappa) / rob.tau)
    return torch.where(total > 0, static, torch.ones_like(static))
