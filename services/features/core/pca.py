"""PCA of dense features to K-d codes: fitted on the first keyframes, then frozen (or refitted) and versioned.

Codes are ``z = V(f − μ)`` with V the (K, C) top principal directions (rows); ``f ≈ μ + Vᵀz``. Downstream
scores cos(μ + Vᵀz, t) for a query t in backbone space, so (μ, V) travel on the ``pca`` topic with the
backbone id.

Bases are fitted from running moments (count, Σx, Σxxᵀ in float64), so a refit over many keyframes costs
one (C, C) matrix per keyframe instead of their samples. Retention of a keyframe is the R² of its round
trip: ``1 − ‖f − f̂‖² / ‖f − f̄‖²`` about the keyframe's own mean f̄ (the strict reading of "variance
kept").
"""
from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass
from typing import Literal, NamedTuple

import numpy as np

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PcaParams:
    n_components: int = 32
    """K, the code size."""
    fit_keyframes: int = 5
    """The first basis is fitted on this many first keyframes (fewer if the stream ends earlier)."""
    samples_per_keyframe: int = 4096
    """Grid cells sampled from each fitting keyframe (all when the grid is smaller)."""
    seed: int = 0
    """Seed of the cell sampling, so a replay fits the same basis."""
    refit_below: float = 0.0
    """Refit (new version) when a keyframe keeps less than this fraction of its variance under the current
    basis; 0 = never: the first basis stays frozen. Consumers must translate codes between versions first."""
    refit_window: int = 5
    """A refit uses the latest this many keyframes, the triggering one included (0 = all so far)."""
    first_version: int = 1
    """Version of the first basis; each refit adds one."""

    def __post_init__(self) -> None:
        if self.first_version < 1:
            raise ValueError(f"first_version must be ≥ 1, got {self.first_version}")
        if self.n_components < 1 or self.fit_keyframes < 1 or self.samples_per_keyframe < 1:
            raise ValueError(f"n_components, fit_keyframes and samples_per_keyframe must be ≥ 1, got {self}")
        if not 0.0 <= self.refit_below < 1.0 or self.refit_window < 0:
            raise ValueError(f"refit_below must be in [0, 1) and refit_window ≥ 0, got {self}")


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


class Moments(NamedTuple):
    """Sufficient statistics of a set of (N, C) feature rows."""

    count: int
    """N."""
    total: np.ndarray
    """(C,) float64 Σx."""
    outer: np.ndarray
    """(C, C) float64 Σxxᵀ."""


def _as_rows(features: np.ndarray) -> np.ndarray:
    """(C, h, w) map or (N, C) rows (any array, a CPU tensor too) → (N, C) float32 array."""
    f = np.asarray(features, dtype=np.float32)
    if f.ndim == 3:
        return f.reshape(f.shape[0], -1).T
    if f.ndim == 2:
        return f
    raise ValueError(f"features must be (C, h, w) or (N, C), got {tuple(f.shape)}")


def sample_rows(features: np.ndarray, count: int, generator: np.random.Generator) -> np.ndarray:
    """``count`` random rows (cells) of a (C, h, w) map or (N, C) rows as (≤count, C)."""
    rows = _as_rows(features)
    if rows.shape[0] <= count:
        return rows
    return rows[generator.permutation(rows.shape[0])[:count]]


def moments(samples: np.ndarray) -> Moments:
    """Moments of (N, C) rows or a (C, h, w) map."""
    x = _as_rows(samples).astype(np.float64)
    return Moments(x.shape[0], x.sum(0), x.T @ x)


def merge_moments(parts: list[Moments]) -> Moments:
    """Moments of the union of the row sets summarised by ``parts`` (at least one)."""
    if not parts:
        raise ValueError("no moments to merge")
    return Moments(sum(m.count for m in parts), sum(m.total for m in parts), sum(m.outer for m in parts))


def fit_moments(m: Moments, n_components: int, backbone: str, version: int = 1) -> PcaBasis:
    """Fit a K-component basis to the rows summarised by ``m`` (N ≥ K, C ≥ K)."""
    n, c = m.count, m.total.shape[0]
    if n < n_components or c < n_components:
        raise ValueError(f"need at least K={n_components} samples and channels, got {n}×{c}")
    mean = m.total / n
    cov = (m.outer - n * np.outer(mean, mean)) / max(n - 1, 1)
    evals, evecs = np.linalg.eigh((cov + cov.T) / 2)  # ascending
    order = np.argsort(evals)[::-1][:n_components]
    return PcaBasis(
        version=version,
        backbone=backbone,
        mean=mean.astype(np.float32),
        components=np.ascontiguousarray(evecs[:, order].T, dtype=np.float32),
        explained_variance=evals[order].astype(np.float32),
        total_variance=float(np.clip(evals, 0, None).sum()),
    )


def fit_pca(samples: np.ndarray, n_components: int, backbone: str, version: int = 1) -> PcaBasis:
    """Fit a K-component basis to (N, C) samples (N ≥ K)."""
    return fit_moments(moments(samples), n_components, backbone, version)


def project(basis: PcaBasis, features: np.ndarray) -> np.ndarray:
    """(C, h, w) features → (h, w, K) float16 codes."""
    f = np.asarray(features, dtype=np.float32)
    if f.ndim != 3 or f.shape[0] != basis.mean.shape[0]:
        raise ValueError(f"features must be (C={basis.mean.shape[0]}, h, w), got {tuple(f.shape)}")
    c, h, w = f.shape
    codes = (f.reshape(c, -1).T - basis.mean) @ basis.components.T
    return codes.reshape(h, w, -1).astype(np.float16)


def reconstruct(basis: PcaBasis, codes: np.ndarray) -> np.ndarray:
    """(..., K) codes → (..., C) float32 features μ + Vᵀz."""
    z = np.asarray(codes, dtype=np.float32)
    return basis.mean + z @ basis.components


def retained_variance(
    basis: PcaBasis, samples: np.ndarray, centre: Literal["own", "basis"] = "own"
) -> float:
    """Fraction of the variance of (N, C) rows or a (C, h, w) map kept by the round trip (no float16 step).

    ``centre="own"``: about the samples' own mean (R², can be negative; the strict measure);
    ``"basis"``: about the fitted mean μ (their spread as the basis sees it, mean shift included).
    """
    if centre not in ("own", "basis"):
        raise ValueError(f"centre must be 'own' or 'basis', got {centre!r}")
    # V's rows are orthonormal, so the residual's energy is the offset's less its projection's, and the spread about
    # the own mean is the offset's less N·|mean offset|²: one (N, C) pass and one product instead of a round trip
    # (the check runs on every keyframe, with the backbone, on features' CPU)
    offset = _as_rows(samples).astype(np.float64) - basis.mean.astype(np.float64)
    energy = float(np.einsum("ij,ij->", offset, offset))
    projected = offset @ basis.components.T.astype(np.float64)
    residual = max(energy - float(np.einsum("ij,ij->", projected, projected)), 0.0)
    spread = energy
    if centre == "own":
        shift = offset.mean(0)
        spread = energy - offset.shape[0] * float(shift @ shift)
    return 1.0 - residual / spread


class PcaFitter:
    """Fits the basis on the first keyframes, then keeps it frozen or refits it (pure state, no I/O).

    With ``params.refit_below`` > 0 each later keyframe's retention under the current basis is checked; below
    the threshold a new version is fitted on the latest ``refit_window`` keyframes (this one included), so the
    keyframe is coded with a basis that has seen it.
    """

    def __init__(self, params: PcaParams, backbone: str):
        self.params, self.backbone = params, backbone
        self._gen = np.random.default_rng(params.seed)
        self._all: Moments | None = None
        self._recent: deque[Moments] = deque(maxlen=max(params.refit_window, 1))
        self._n_collected = 0
        self.basis: PcaBasis | None = None
        self.last_retention: float | None = None
        """Retention of the latest keyframe under the basis it is coded with (None before the first fit)."""
        self._version = params.first_version - 1

    @property
    def ready(self) -> bool:
        return self.basis is not None

    def add(self, features: np.ndarray) -> PcaBasis | None:
        """Add one keyframe's (C, h, w) features; returns a basis when this keyframe made a new one."""
        if self.basis is None:
            self._collect(features)
            if self._n_collected < self.params.fit_keyframes:
                return None
            basis = self.fit_now()
            self.last_retention = retained_variance(basis, features)
            return basis
        kept = retained_variance(self.basis, features)
        self.last_retention = kept
        if self.params.refit_below <= 0.0:
            return None
        self._collect(features)
        if kept >= self.params.refit_below:
            return None
        basis = self._fit(self._window_moments())
        self.last_retention = retained_variance(basis, features)
        log.info("pca refit", extra={"version": basis.version, "kept_before": round(kept, 4),
                                     "kept_after": round(self.last_retention, 4)})
        return basis

    def fit_now(self) -> PcaBasis:
        """Fit on what was collected (also on an early end of stream)."""
        if self._all is None:
            raise ValueError("no keyframe features collected yet")
        return self._fit(self._all)

    def _collect(self, features: np.ndarray) -> None:
        m = moments(sample_rows(features, self.params.samples_per_keyframe, self._gen))
        self._all = m if self._all is None else merge_moments([self._all, m])
        if self.params.refit_below > 0.0 and self.params.refit_window > 0:
            self._recent.append(m)
        self._n_collected += 1

    def _window_moments(self) -> Moments:
        return self._all if self.params.refit_window == 0 else merge_moments(list(self._recent))

    def _fit(self, m: Moments) -> PcaBasis:
        self._version += 1
        self.basis = fit_moments(m, self.params.n_components, self.backbone, self._version)
        return self.basis
