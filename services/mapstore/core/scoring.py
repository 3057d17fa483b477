"""PCA bases of the map's codes and the numpy side of scoring them (the top k of a score vector, a reference
decoder). The scores themselves come from :class:`services.mapstore.core.index.ScoringIndex`, in torch, which a
mapstore imports only once it is queried (a map that is only built never loads torch).

Cosine scores of backbone-space query vectors against PCA-coded points, without decoding them: with basis
(μ: (D,), V: (K, D)) a code z decodes to f = μ + Vᵀz, and for a query t
    cos(f, t) = (μ·t + z·(V t)) / (‖f‖ ‖t‖),   ‖f‖² = ‖μ‖² + 2 z·(Vμ) + zᵀ(V Vᵀ)z.
Per point we precompute a = [z/‖f‖, 1/‖f‖] (N, K+1); per query b = [V t, μ·t]/‖t‖ (K+1,),
so the scores are one matrix product a·bᵀ.

Points without a code (voxels only keyframes whose codes have not arrived saw) are absent from scoring: their
score is NaN, they are never among the top k, and `argmax` gives them label −1 (not the score of the zero code,
which would be the PCA mean's).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

EPS = 1e-12  # floor of norms (a decoded feature squared, a query) before dividing by them


@dataclass(frozen=True)
class PcaBasis:
    """A versioned PCA basis of backbone features.

    Fields: version (int); mean (D,) float32 μ; components (K, D) float32 V (rows = components);
    backbone: id of the backbone whose D-d features the basis compresses.
    """

    version: int
    mean: np.ndarray
    components: np.ndarray
    backbone: str = ""

    def __post_init__(self) -> None:
        if self.mean.ndim != 1 or self.components.ndim != 2 or self.components.shape[1] != self.mean.shape[0]:
            raise ValueError(f"basis needs mean (D,) and components (K, D); got {self.mean.shape}, "
                             f"{self.components.shape}")

    @property
    def dim(self) -> int:
        """D, the backbone feature size."""
        return int(self.mean.shape[0])

    @property
    def rank(self) -> int:
        """K, the code size."""
        return int(self.components.shape[0])


class TopK(NamedTuple):
    """Best points per query."""

    indices: np.ndarray  # (Q, k) int64 point indices, best first
    scores: np.ndarray  # (Q, k) float32 cosine scores



def best_of(scores: np.ndarray, k: int, above: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The k highest finite scores of one query, best first (ties: lower index first).

    Args:
        scores: (N,) float scores, NaN for points that take no part.
        k: how many (fewer come back when fewer scores are finite).
        above: (M,) int64 indices of every point scoring at least some cut, or None. When M >= k the k best are
            among them (every other point scores below the cut), so only M scores are ranked, not N.
    Returns:
        indices (k,) int64 and scores (k,) float32.
    """
    pool = above if above is not None and above.size >= k else None
    vals = scores if pool is None else scores[pool]
    k = min(k, int(vals.size))
    if k <= 0:
        return np.zeros(0, np.int64), np.zeros(0, np.float32)
    # the k-th best value (partition sorts NaN last, so on −scores the k smallest are the k best finite ones),
    # then every point at least as good, so that ties at the k-th value are broken by index, not by partition
    kth = -np.partition(-vals, k - 1)[k - 1] if k < vals.size else np.nan
    if np.isnan(kth):  # k reaches past the finite scores: all of them
        kth = np.fmin.reduce(vals)
    part = np.flatnonzero(vals >= kth)  # increasing: the stable sort below keeps lower indices first
    part = part[np.argsort(-vals[part], kind="stable")][:k]
    idx = part if pool is None else pool[part]
    return idx.astype(np.int64), np.asarray(scores[idx], np.float32)


def decode_codes(codes: np.ndarray, basis: PcaBasis) -> np.ndarray:
    """Reference decoder: (N, K) codes → (N, D) float64 features μ + Vᵀz."""
    return basis.mean.astype(np.float64) + codes.astype(np.float64) @ basis.components.astype(np.float64)
