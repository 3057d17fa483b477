"""What a BA's IRLS freezes for one Levenberg-Marquardt iteration: ARK's code cosine at the reprojections, the
robust shape of every pixel (ARK's from that cosine, or the fixed kernel's), its Barron constants, and the
embedding term's weight. Edges without codes at both ends keep the fixed kernel and no embedding term (a keyframe's
codes follow its geometry, so a BA's newest keyframe often has none yet)."""
from __future__ import annotations

from typing import NamedTuple

import torch

from services.ba.core import ark as ark_codes
from services.ba.core import embedding, robust
from services.ba.core.params import BAParams
from services.ba.core.slice_fields import one_value

class Frozen(NamedTuple):
    """IRLS quantities frozen within one iteration."""

    alpha: torch.Tensor  # (E, P) robust shape
    kernel: robust.Kernel | None  # the Barron constants of alpha; None: formed from it a slice at a time (`sliced`)
    embed_weight: torch.Tensor  # (E, P) weight of the embedding residual (0 where unused)


def code_cosine(codes: torch.Tensor | None, ii: torch.Tensor, jj: torch.Tensor, coded: torch.Tensor | None,
                coords: torch.Tensor, in_front: torch.Tensor, embed: embedding.EmbeddingResidual | None,
                params: BAParams, cache: ark_codes.ArkCosine | None) -> ark_codes.ArkCosine | None:
    """Code cosine at the reprojections ``coords`` (E, 2, P) (None without ARK or codes): from the embedding
    residual when that term is on (it is evaluated anyway), else from the lazily refreshed ``cache``. An edge
    without codes at both ends (``coded`` (E,) bool; None: every edge has them) has no valid cosine: its pixels
    are no evidence for ``static_weight``."""
    if not params.robust.use_ark or codes is None:
        return None
    if embed is not None:
        ark = ark_codes.ArkCosine(embed.cosine, embed.valid, coords)
    else:
        ark = ark_codes.refresh(cache, codes, ii, jj, coords, in_front, params.robust.ark_refresh_px)
    return ark if coded is None else ark._replace(valid=ark.valid & coded[:, None])


def frozen(flow_norm: torch.Tensor, flow_w: torch.Tensor, embed: embedding.EmbeddingResidual | None,
           params: BAParams, ark: ark_codes.ArkCosine | None, coded: torch.Tensor | None = None) -> Frozen:
    """The IRLS quantities of evaluated residuals (flow norms and weights (E, P), the embedding residual);
    ``coded`` (E,) bool: the edges with codes at both ends (None: all), the others keep the fixed kernel and have
    no embedding term."""
    rob = params.robust
    if ark is not None and rob.ark_in_solve:
        alpha = robust.ark_shape(ark.cosine, rob)  # today's centred map or the paper's (RobustParams.ark_mode)
        if coded is not None:
            alpha = torch.where(coded[:, None], alpha, alpha.new_tensor(rob.fixed_alpha))
        kern = robust.kernel(alpha, alpha.dtype, alpha.device)
    else:  # one shape everywhere: its constants formed once and broadcast (views), not ~6 (E, P) tensors
        alpha, kern = uniform(flow_w, rob.fixed_alpha)
    if embed is None or params.lambda_embed <= 0:
        return Frozen(alpha, kern, flow_w.new_zeros((1,) * flow_w.dim()).expand_as(flow_w))
    # The embedding term is trusted only where the pixel looks static: its flow IRLS weight times the ARK
    # probability of "same content" (the sigmoid of cs); otherwise a moving or occluded pixel's codes would
    # pull the geometry just as its flow does.
    static = rob.scale**2 * robust.weight(flow_norm, kern, rob.scale)
    same = torch.sigmoid((embed.cosine - rob.kappa) / rob.tau)
    weight = params.lambda_embed * flow_w * embed.valid * static * same
    return Frozen(alpha, kern, weight if coded is None else weight * coded[:, None])


def uniform(like: torch.Tensor, alpha: float) -> tuple[torch.Tensor, robust.Kernel]:
    """``alpha`` and its kernel as broadcast views of ``like``'s shape (no per-pixel memory)."""
    one = torch.full((1,) * like.dim(), alpha, dtype=like.dtype, device=like.device)
    kern = robust.kernel(one, one.dtype, one.device)
    return one.expand_as(like), robust.Kernel(*(None if t is None else t.expand_as(like) for t in kern))


def lazy(alpha: torch.Tensor, embed_weight: torch.Tensor) -> Frozen:
    """The quantities of a BA linearised in slices, which keeps per-pixel shapes ``alpha`` (E, P) and forms their
    kernel constants a slice at a time where they are used: four float and three bool fields of every edge were
    ~50 MB of an 840-edge background BA's peak. A fixed shape keeps its broadcast constants (no memory)."""
    if one_value(alpha):
        return Frozen(*uniform(alpha, float(alpha.reshape(-1)[0])), embed_weight)
    return Frozen(alpha, None, embed_weight)


def sliced(quantities: Frozen, edges: slice) -> Frozen:
    """The quantities of the edges in ``edges``, with their kernel constants."""
    alpha = quantities.alpha[edges]
    if quantities.kernel is None:
        kern = robust.kernel(alpha, alpha.dtype, alpha.device)
    else:
        kern = robust.Kernel(*(None if t is None else t[edges] for t in quantities.kernel))
    return Frozen(alpha, kern, quantities.embed_weight[edges])
