"""ARK's code cosine (services/ba/core/ark.py) against torch's own bilinear sampling, over more edges than one
sampling chunk, and the lazy cache's refresh rule."""
from __future__ import annotations

import torch
import torch.nn.functional as F

from services.ba.core import ark


def _world(n_kf: int = 5, h: int = 6, w: int = 8, k: int = 4, n_edges: int = ark.EDGE_CHUNK * 2 + 5, seed: int = 0):
    gen = torch.Generator().manual_seed(seed)
    codes = torch.randn(n_kf, h, w, k, generator=gen)
    ii = torch.randint(0, n_kf, (n_edges,), generator=gen)
    jj = (ii + torch.randint(1, n_kf, (n_edges,), generator=gen)) % n_kf
    # most reprojections inside the target map, some outside it (flagged invalid)
    x = torch.rand(n_edges, h * w, generator=gen) * (w + 1) - 1.0
    y = torch.rand(n_edges, h * w, generator=gen) * (h + 1) - 1.0
    return codes, ii, jj, torch.stack([x, y], 1).double()


def _reference(codes, ii, jj, coords):
    """Cosine of each source pixel's code and the target map sampled by F.grid_sample at ``coords``."""
    n_kf, h, w, k = codes.shape
    maps = codes.permute(0, 3, 1, 2)[jj]  # (E, K, h, w)
    grid = torch.stack([2 * coords[:, 0] / (w - 1) - 1, 2 * coords[:, 1] / (h - 1) - 1], -1)[:, None].float()
    sampled = F.grid_sample(maps, grid, mode="bilinear", align_corners=True)[:, :, 0].transpose(1, 2)  # (E, P, K)
    source = codes.reshape(n_kf, h * w, k)[ii]
    cosine = F.cosine_similarity(source, sampled, dim=-1)
    x, y = coords[:, 0], coords[:, 1]
    inside = (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1)
    return cosine, inside


def test_sample_matches_grid_sample_over_several_chunks():
    codes, ii, jj, coords = _world()
    out = ark.sample(codes, ii, jj, coords)
    cosine, inside = _reference(codes, ii, jj, coords)
    assert out.cosine.shape == cosine.shape and out.cosine.dtype == coords.dtype
    assert torch.equal(out.valid, inside)
    assert 0 < int(inside.sum()) < inside.numel()
    torch.testing.assert_close(out.cosine[inside], cosine[inside].double(), atol=1e-5, rtol=0)
    assert out.coords is coords


def test_refresh_resamples_only_the_edges_that_moved():
    codes, ii, jj, coords = _world(seed=1)
    valid = torch.ones(coords.shape[0], coords.shape[2], dtype=torch.bool)
    cache = ark.sample(codes, ii, jj, coords)
    moved = coords.clone()
    moved[3, 0] += 0.5  # one edge moves half a grid px, another a hundredth
    moved[7, 1] += 0.01
    out = ark.refresh(cache, codes, ii, jj, moved, valid, refresh_px=0.25)
    fresh = ark.sample(codes, ii, jj, moved)
    torch.testing.assert_close(out.cosine[3], fresh.cosine[3])
    torch.testing.assert_close(out.coords[3], moved[3])
    keep = torch.ones(len(ii), dtype=torch.bool)
    keep[3] = False
    assert torch.equal(out.cosine[keep], cache.cosine[keep])  # edge 7 moved less than refresh_px: kept as sampled
    assert torch.equal(out.coords[7], coords[7])
    assert not torch.equal(cache.cosine[3], fresh.cosine[3])  # the move changed what edge 3 sees
    # nothing moved: the cache itself comes back; refresh_px 0 samples every edge
    assert ark.refresh(cache, codes, ii, jj, coords, valid, refresh_px=0.25) is cache
    torch.testing.assert_close(ark.refresh(cache, codes, ii, jj, moved, valid, 0.0).cosine, fresh.cosine)
