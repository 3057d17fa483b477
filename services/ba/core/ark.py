"""Code similarity behind the ARK kernel: cosine of a pixel's code and the code map of the other view at its
reprojection, re-sampled lazily per edge.

ARK shapes are frozen within a Levenberg-Marquardt iteration (IRLS). Sampling the ``(E, P, K)`` codes is the
most expensive step of an iteration on a CPU, yet once the window is near its optimum an update moves most
reprojections by a small fraction of a grid cell, and the bilinearly interpolated codes -- hence the cosine --
barely change. So an edge is re-sampled only once some reprojection of it has moved more than
``refresh_px`` since its last sample; ``refresh_px = 0`` re-samples every edge at every linearisation.
"""
from __future__ import annotations

from typing import NamedTuple

import torch

from services.ba.core import embedding


EDGE_CHUNK = 16  # edges sampled at once


class ArkCosine(NamedTuple):
    """Per edge ``e`` and source pixel ``p``."""

    cosine: torch.Tensor  # (E, P) in [-1, 1]: cosine of the source code and the target map at ``coords``
    valid: torch.Tensor  # (E, P) bool: ``coords`` fell inside the target code map
    coords: torch.Tensor  # (E, 2, P) the reprojections at which the codes were sampled (grid px)


def sample(codes: torch.Tensor, ii: torch.Tensor, jj: torch.Tensor, coords: torch.Tensor) -> ArkCosine:
    """Cosine similarity for every edge.

    Args:
        codes: ``(N, h, w, K)`` float code maps; fastest as a view of channels-first ``(N, K, h, w)`` storage,
            which this samples without a copy (``ba._prepare``).
        ii, jj: ``(E,)`` long source / target keyframe of each edge.
        coords: ``(E, 2, P)`` reprojections of the source grid pixels into the target (grid px).
    """
    n, h, w, k = codes.shape
    if coords.shape[1:] != (2, h * w) or ii.shape != jj.shape or coords.shape[0] != ii.shape[0]:
        raise ValueError(f"coords (E, 2, {h * w}) and ii, jj (E,) expected, got {tuple(coords.shape)}, "
                         f"{tuple(ii.shape)}, {tuple(jj.shape)}")
    # channels first, for grid_sample: ~3x faster than embedding.bilinear_sample's corner gathers, which the
    # embedding term keeps for their exact derivatives (an ARK sample of every edge was a quarter of a background
    # BA's time)
    maps = codes.permute(0, 3, 1, 2).contiguous()  # no copy when the storage is channels first already
    flat = maps.view(n, k, h * w)
    scale = coords.new_tensor([2.0 / max(w - 1, 1), 2.0 / max(h - 1, 1)])[:, None]
    # the outputs exist before the chunks' temporaries: small per-chunk results kept between them sat in the freed
    # heap and pushed every next chunk's temporaries above it (a 100-keyframe global BA peaked ~70 MB higher)
    cosine = coords.new_empty((len(ii), h * w))
    valid = torch.empty((len(ii), h * w), dtype=torch.bool, device=coords.device)
    # a few edges at a time: a sample holds a few (E, K, P) temporaries, GBs for an end-of-stream BA's edges at once
    for start in range(0, len(ii), EDGE_CHUNK):
        part = slice(start, start + EDGE_CHUNK)
        # a point behind a camera projects to NaN: sampled at the border, and not valid
        at = torch.nan_to_num(coords[part], nan=-1.0, posinf=-1.0, neginf=-1.0)
        x, y = at[:, 0], at[:, 1]
        valid[part] = (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1)
        # (e, 1, P, 2) in [-1, 1], made contiguous: grid_sample reads a strided grid ~25 % slower
        grid = (at * scale - 1).transpose(1, 2)[:, None].to(maps.dtype).contiguous()
        values = torch.nn.functional.grid_sample(maps.index_select(0, jj[part]), grid, mode="bilinear",
                                                 padding_mode="border", align_corners=True)[:, :, 0]
        source = flat.index_select(0, ii[part])
        # sums of squares, not norm(dim=1): torch's norm over the strided channel axis is ~30x slower on CPU
        norms = (source.square().sum(1).sqrt_().clamp_min_(embedding.TINY)
                 * values.square().sum(1).sqrt_().clamp_min_(embedding.TINY))
        cosine[part] = ((source * values).sum(1) / norms).clamp(-1, 1)
        del values, source, norms  # freed before the next chunk's temporaries are allocated
    # coords is a fresh tensor of the caller's evaluation, never written in place: kept without a copy
    return ArkCosine(cosine, valid, coords)


def refresh(cache: ArkCosine | None, codes: torch.Tensor, ii: torch.Tensor, jj: torch.Tensor,
            coords: torch.Tensor, valid: torch.Tensor, refresh_px: float) -> ArkCosine:
    """``cache`` brought up to date with reprojections ``coords`` ``(E, 2, P)``: edges where a pixel in front
    of the target camera (``valid`` ``(E, P)``) moved more than ``refresh_px`` since the cache's sample are
    re-sampled; the others keep their cosine. ``cache`` None (or a different edge count) samples every edge."""
    if cache is None or cache.cosine.shape[0] != ii.shape[0] or refresh_px <= 0:
        return sample(codes, ii, jj, coords)
    moved = torch.nan_to_num((coords - cache.coords).abs().amax(1), nan=float("inf"))
    stale = torch.nonzero(torch.where(valid, moved, torch.zeros_like(moved)).amax(1) > refresh_px)[:, 0]
    if stale.numel() == 0:
        return cache
    fresh = sample(codes, ii[stale], jj[stale], coords[stale])
    cosine, inside, at = cache.cosine.clone(), cache.valid.clone(), cache.coords.clone()
    cosine[stale], inside[stale], at[stale] = fresh.cosine, fresh.valid, fresh.coords
    return ArkCosine(cosine, inside, at)
