"""PCA of dense features to K-d codes: fitted once on the first keyframes, then frozen and versioned.

Codes are ``z = Vᵀ(f − μ)`` with V the top-K principal directions; ``f ≈ μ + V z``. Downstream scores
cos(μ + Vz, t) for a query t in backbone space, so (μ, V) travel on the ``pca`` topic with the backbone id.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch


@dataclass(frozen=True)
class PcaParams:
    n_components: int = 32
    """K, the code size."""
    fit_keyframes: int = 5
    """The basis is fitted on this many first keyframes (fewer if the stream ends earlier), then frozen."""
    samples_per_keyframe: int = 4096
    """Grid cells sampled from each fitting keyframe (all when the grid is smaller)."""
    seed: int = 0
    """Seed of the cell sampling, so a replay fits the same basis."""


class PcaBasis(NamedTuple):
    version: int
    """Increases by one with every refit within a stream."""
    backbone: str
    """Output space of the features the basis was fitted on (e.g. ``dinov2_vits14``)."""
    mean: np.ndarray
    """(C,) float32 μ."""
    components: np.ndarray
    """(K, C) float32 V (rows orthonormal)."""
    explained_variance: np.ndarray
    """(K,) float32 variance along each component on the fitting set."""
    total_variance: float
    """Total variance of the fitting set (sum over all C dimensions)."""


def _as_rows(features: torch.Tensor | np.ndarray) -> torch.Tensor:
    """(C, h, w) map or (N, C) rows → (N, C) float32 tensor."""
    f = torch.as_tensor(features).float()
    if f.ndim == 3:
        return f.reshape(f.shape[0], -1).T
    if f.ndim == 2:
        return f
    raise ValueError(f"features must be (C, h, w) or (N, C), got {tuple(f.shape)}")


def sample_rows(features: torch.Tensor, count: int, generator: torch.Generator) -> torch.Tensor:
    """``count`` random rows (cells) of a (C, h, w) map as (≤count, C)."""
    rows = _as_rows(features)
    if rows.shape[0] <= count:
        return rows
    return rows[torch.randperm(rows.shape[0], generator=generator)[:count]]


def fit_pca(samples: torch.Tensor, n_components: int, backbone: str, version: int = 1) -> PcaBasis:
    """Fit a K-component basis to (N, C) samples (N ≥ K)."""
    x = _as_rows(samples).double()
    n, c = x.shape
    if n < n_components or c < n_components:
        raise ValueError(f"need at least K={n_components} samples and channels, got {n}×{c}")
    mean = x.mean(0)
    cov = (x - mean).T @ (x - mean) / max(n - 1, 1)
    evals, evecs = torch.linalg.eigh(cov)  # ascending
    order = torch.argsort(evals, descending=True)[:n_components]
    return PcaBasis(
        version=version,
        backbone=backbone,
        mean=mean.float().numpy(),
        components=evecs[:, order].T.float().contiguous().numpy(),
        explained_variance=evals[order].float().numpy(),
        total_variance=float(evals.clamp_min(0).sum()),
    )


def project(basis: PcaBasis, features: torch.Tensor) -> np.ndarray:
    """(C, h, w) features → (h, w, K) float16 codes."""
    f = torch.as_tensor(features).float()
    if f.ndim != 3 or f.shape[0] != basis.mean.shape[0]:
        raise ValueError(f"features must be (C={basis.mean.shape[0]}, h, w), got {tuple(f.shape)}")
    c, h, w = f.shape
    rows = f.reshape(c, -1).T - torch.from_numpy(basis.mean)
    codes = rows @ torch.from_numpy(basis.components).T
    return codes.reshape(h, w, -1).numpy().astype(np.float16)


def reconstruct(basis: PcaBasis, codes: np.ndarray) -> np.ndarray:
    """(..., K) codes → (..., C) float32 features μ + Vz."""
    z = np.asarray(codes, dtype=np.float32)
    return basis.mean + z @ basis.components


def retained_variance(basis: PcaBasis, samples: torch.Tensor | np.ndarray) -> float:
    """Fraction of the variance of (N, C) ``samples`` (about their own mean) kept by the round trip."""
    x = _as_rows(samples).numpy().astype(np.float64)
    centred = x - x.mean(0)
    residual = x - reconstruct(basis, (x - basis.mean) @ basis.components.T)
    return float(1.0 - (residual**2).sum() / (centred**2).sum())


class PcaFitter:
    """Collects samples from the first keyframes and fits the basis once (pure state, no I/O)."""

    def __init__(self, params: PcaParams, backbone: str):
        self.params, self.backbone = params, backbone
        self._samples: list[torch.Tensor] = []
        self._gen = torch.Generator().manual_seed(params.seed)
        self.basis: PcaBasis | None = None
        self._version = 0

    @property
    def ready(self) -> bool:
        return self.basis is not None

    def add(self, features: torch.Tensor) -> PcaBasis | None:
        """Add one keyframe's (C, h, w) features; returns the basis when this keyframe completes the fit."""
        if self.basis is not None:
            return None
        self._samples.append(sample_rows(features, self.params.samples_per_keyframe, self._gen))
        if len(self._samples) >= self.params.fit_keyframes:
            return self.fit_now()
        return None

    def fit_now(self) -> PcaBasis:
        """Fit on what was collected (early end of stream); the basis is frozen from here on."""
        if not self._samples:
            raise ValueError("no keyframe features collected yet")
        self._version += 1
        self.basis = fit_pca(torch.cat(self._samples), self.params.n_components, self.backbone, self._version)
        self._samples.clear()
        return self.basis
