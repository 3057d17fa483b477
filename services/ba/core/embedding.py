"""Bilinear sampling of code maps with exact spatial derivatives; the code-similarity residual.

Code maps are ``(N, h, w, K)`` (channels last, grid pixel centres at integer coordinates). Bilinear
interpolation is piecewise linear, so its derivatives are exact inside each cell (one-sided on cell borders).
"""
from __future__ import annotations

from typing import NamedTuple

import torch

# Guard for norms / chordal residual near zero.
TINY = 1e-12


class CodeSample(NamedTuple):
    """Bilinear sample of target code maps at reprojected coordinates."""

    values: torch.Tensor  # (E, P, K)
    d_dx: torch.Tensor | None  # (E, P, K) derivative w.r.t. x (grid px); None if not asked for
    d_dy: torch.Tensor | None  # (E, P, K) derivative w.r.t. y (grid px); None if not asked for
    inside: torch.Tensor  # (E, P) bool: coords within [0, w-1] x [0, h-1]


class EmbeddingResidual(NamedTuple):
    """Per edge and pixel: cosine similarity, the residual and its derivative w.r.t. the target coords."""

    cosine: torch.Tensor  # (E, P) in [-1, 1]
    residual: torch.Tensor  # (E, P)
    d_coords: torch.Tensor | None  # (E, P, 2) d residual / d (x, y); None without sample derivatives
    valid: torch.Tensor  # (E, P) bool


def bilinear_sample(code_maps: torch.Tensor, index: torch.Tensor, coords: torch.Tensor,
                    derivatives: bool = True) -> CodeSample:
    """Sample ``code_maps[index[e]]`` at ``coords[e]``.

    Args:
        code_maps: ``(N, h, w, K)`` float; the sample is computed in this dtype (float32 halves the memory
            traffic of this, the most expensive step of the embedding term).
        index: ``(E,)`` long, which map each edge samples.
        coords: ``(E, P, 2)`` grid coordinates ``(x, y)``; outside points are clamped and flagged.
        derivatives: also return the spatial derivatives.
    """
    n, h, w, k = code_maps.shape
    if coords.shape[0] != index.shape[0] or coords.shape[-1] != 2:
        raise ValueError(f"coords (E,P,2) with E = len(index) expected, got {coords.shape}, {index.shape}")
    # a point behind a camera projects to NaN; NaN survives clamp() and becomes a wild index after long()
    coords = torch.nan_to_num(coords, nan=-1.0, posinf=-1.0, neginf=-1.0)
    x, y = coords[..., 0], coords[..., 1]
    inside = (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1)
    x0 = x.clamp(0, w - 1).floor().clamp(max=max(w - 2, 0))
    y0 = y.clamp(0, h - 1).floor().clamp(max=max(h - 2, 0))
    fx = (x.clamp(0, w - 1) - x0)[..., None].to(code_maps.dtype)
    fy = (y.clamp(0, h - 1) - y0)[..., None].to(code_maps.dtype)
    table = code_maps.reshape(n * h * w, k)
    rows = (index[:, None] * (h * w) + (y0 * w + x0).long()).reshape(-1)
    # index_select of whole K-rows is about 2x faster than advanced indexing here
    corner = lambda offset: table.index_select(0, rows + offset).view(*coords.shape[:2], k)  # noqa: E731
    v00, v01, v10, v11 = corner(0), corner(1), corner(w), corner(w + 1)
    # few full-size temporaries: this is memory-bound at (E, P, K)
    d_top, d_bottom = v01 - v00, v11 - v10
    top = torch.addcmul(v00, fx, d_top)
    d_dy = torch.addcmul(v10, fx, d_bottom).sub_(top)
    values = torch.addcmul(top, fy, d_dy)
    if not derivatives:
        return CodeSample(values, None, None, inside)
    d_dx = torch.addcmul(d_top, fy, d_bottom.sub_(d_top))
    return CodeSample(values, d_dx, d_dy, inside)


def embedding_residual(source_codes: torch.Tensor, sample: CodeSample, form: str = "angular") -> EmbeddingResidual:
    """Residual between source codes ``(E, P, K)`` and sampled target codes.

    ``form="angular"``: ``r = 1 - cs``; ``form="chordal"``: ``r = sqrt(2 (1 - cs))`` (the distance between
    unit vectors). ``cs`` is the cosine similarity.
    """
    a, yv = source_codes, sample.values
    na = a.norm(dim=-1).clamp_min(TINY)
    ny = yv.norm(dim=-1).clamp_min(TINY)
    cs = (a * yv).sum(-1) / (na * ny)
    if sample.d_dx is None:
        residual = 1 - cs if form == "angular" else torch.sqrt((2 * (1 - cs)).clamp_min(0))
        return EmbeddingResidual(cs.clamp(-1, 1), residual, None, sample.inside)
    dcs_dy = a / (na * ny)[..., None] - cs[..., None] * yv / (ny**2)[..., None]
    dcs_dc = torch.stack([(dcs_dy * sample.d_dx).sum(-1), (dcs_dy * sample.d_dy).sum(-1)], -1)
    if form == "angular":
        residual, d_coords = 1 - cs, -dcs_dc
    elif form == "chordal":
        residual = torch.sqrt((2 * (1 - cs)).clamp_min(0))
        d_coords = -dcs_dc / residual.clamp_min(1e-6)[..., None]
    else:
        raise ValueError(f"form must be 'angular' or 'chordal', got {form!r}")
    # outside the map the sample is clamped: no usable gradient
    d_coords = d_coords * sample.inside[..., None]
    return EmbeddingResidual(cs.clamp(-1, 1), residual, d_coords, sample.inside)


def uncentred_codes(codes: torch.Tensor, mean: torch.Tensor, components: torch.Tensor) -> torch.Tensor:
    """Codes whose cosine similarity is that of the backbone features they reconstruct, not of the centred codes.

    A PCA basis (mean ``mu`` (D,), orthonormal rows ``V`` (K, D)) codes a feature as ``z = V (f - mu)``, so the
    cosine of two codes ignores the mean feature that all DINO features share: centred codes of unrelated
    surfaces are near orthogonal, their raw features are not. KM-ViPE's reference kernel thresholds the raw
    cosine (cs < 0.4), which the reconstructions ``f = mu + V^T z`` give exactly: with ``m = V mu`` and
    ``r = |mu - V^T m|``, ``f_a . f_b = (z_a + m) . (z_b + m) + r^2``, i.e. the dot product of ``[z + m, r]``.

    Args:
        codes: ``(..., K)`` centred PCA codes.
        mean: ``(D,)`` the basis mean ``mu``.
        components: ``(K, D)`` the basis rows ``V``.
    Returns:
        ``(..., K + 1)`` codes in ``codes``' dtype.
    """
    if components.shape[0] != codes.shape[-1] or components.shape[1:] != mean.shape:
        raise ValueError(f"codes (..., K), mean (D,), components (K, D) expected, got {tuple(codes.shape)}, "
                         f"{tuple(mean.shape)}, {tuple(components.shape)}")
    mu, v = mean.double(), components.double()
    m = v @ mu
    rest = (mu - v.T @ m).norm()
    shifted = codes + m.to(codes)
    return torch.cat([shifted, rest.to(codes).expand(*codes.shape[:-1], 1)], -1)
