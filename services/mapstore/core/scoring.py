"""Cosine scores of backbone-space query vectors against PCA-coded points, without decoding them.

With basis (μ: (D,), V: (K, D)) a code z decodes to f = μ + Vᵀz, and for a query t
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
import torch

from services.common.device import resolve_device

_EPS = 1e-12


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


class ScoringIndex:
    """Precomputed per-point terms for scoring N points against query vectors."""

    def __init__(self, codes: np.ndarray, basis: PcaBasis, device: str = "auto",
                 valid: np.ndarray | None = None) -> None:
        """
        Args:
            codes: (N, K) float codes of the points (PCA space of `basis`).
            basis: the basis the codes were made with.
            device: torch device name or "auto".
            valid: (N,) bool, the points that have a code (None: all, except non-finite codes); the others score
                NaN and are never ranked.
        """
        if codes.ndim != 2 or codes.shape[1] != basis.rank:
            raise ValueError(f"codes must be (N, {basis.rank}), got {codes.shape}")
        self.basis = basis
        self.device = resolve_device(device)
        v = basis.components.astype(np.float64)
        mu = basis.mean.astype(np.float64)
        z = codes.astype(np.float64)
        ok = np.all(np.isfinite(z), axis=1)
        if valid is not None:
            if np.shape(valid) != ok.shape:
                raise ValueError(f"valid must be ({codes.shape[0]},), got {np.shape(valid)}")
            ok &= np.asarray(valid, bool)
        z = np.where(ok[:, None], z, 0.0)
        self.n_valid = int(ok.sum())
        self._absent = None if ok.all() else torch.from_numpy(~ok).to(self.device)
        self._absent_idx = np.flatnonzero(~ok)  # few in practice: NaN is written only there (score)
        norm2 = mu @ mu + 2.0 * z @ (v @ mu) + np.einsum("nk,kl,nl->n", z, v @ v.T, z)
        inv = 1.0 / np.sqrt(np.maximum(norm2, _EPS))
        a = np.concatenate([z * inv[:, None], inv[:, None]], axis=1).astype(np.float32)
        self._a = torch.from_numpy(a).to(self.device)
        self._v = torch.from_numpy(basis.components.astype(np.float32)).to(self.device)
        self._mu = torch.from_numpy(basis.mean.astype(np.float32)).to(self.device)

    def __len__(self) -> int:
        return int(self._a.shape[0])

    def _query_terms(self, queries: np.ndarray) -> torch.Tensor:
        q = np.array(queries, dtype=np.float32)  # a writable copy: torch refuses read-only buffers
        if q.ndim == 1:
            q = q[None]
        if q.ndim != 2 or q.shape[1] != self.basis.dim:
            raise ValueError(f"queries must be (Q, {self.basis.dim}) or ({self.basis.dim},), got {q.shape}")
        t = torch.from_numpy(q).to(self.device)
        b = torch.cat([t @ self._v.T, (t @ self._mu)[:, None]], dim=1)
        return b / t.norm(dim=1, keepdim=True).clamp_min(_EPS)

    def score(self, queries: np.ndarray) -> np.ndarray:
        """Cosine scores of every point for each query.

        One matrix-vector product of the (N, K+1) per-point terms per query, then NaN written at the points
        without a code (no masking pass over N). Per query rather than one (Q, K+1)·(K+1, N) product: with K+1
        columns that product takes 3-10x longer than Q products on CPU (measured with torch 2.x on 2 cores).

        Args:
            queries: (Q, D) or (D,) float query vectors in backbone space.
        Returns:
            (Q, N) float32 cosine similarities (a fresh, writable array), NaN for points without a code.
        """
        b = self._query_terms(queries)
        s = torch.empty((b.shape[0], len(self)), dtype=self._a.dtype, device=self.device)
        for i in range(b.shape[0]):
            torch.mv(self._a, b[i], out=s[i])
        s = s.cpu().numpy()
        if self._absent_idx.size:
            s[:, self._absent_idx] = np.nan
        return s

    def _blocks(self, queries: np.ndarray, chunk: int):
        """(start, (Q, n) scores of points start..start+n); points without a code score −inf here."""
        b = self._query_terms(queries)
        for start in range(0, len(self), chunk):
            s = b @ self._a[start : start + chunk].T
            if self._absent is not None:
                s = s.masked_fill(self._absent[None, start : start + chunk], float("-inf"))
            yield start, s

    def topk(self, queries: np.ndarray, k: int, chunk: int = 262_144) -> TopK:
        """The k best points per query, scored in blocks of `chunk` points (no Q×N matrix).

        Returns:
            TopK with (Q, min(k, points with a code)) indices and scores, best first.
        """
        k = min(k, self.n_valid)
        if k <= 0:
            q = 1 if np.asarray(queries).ndim == 1 else len(queries)
            return TopK(np.zeros((q, 0), np.int64), np.zeros((q, 0), np.float32))
        best_s: torch.Tensor | None = None
        best_i: torch.Tensor | None = None
        for start, s in self._blocks(queries, chunk):
            s_top, i_top = s.topk(min(k, s.shape[1]), dim=1)
            i_top = i_top + start
            if best_s is not None:
                s_top, sel = torch.cat([best_s, s_top], 1).topk(k, dim=1)
                i_top = torch.gather(torch.cat([best_i, i_top], 1), 1, sel)
            best_s, best_i = s_top, i_top
        if best_s is None:
            q = 1 if np.asarray(queries).ndim == 1 else len(queries)
            return TopK(np.zeros((q, 0), np.int64), np.zeros((q, 0), np.float32))
        return TopK(best_i.cpu().numpy(), best_s.cpu().numpy())

    def argmax(self, queries: np.ndarray, chunk: int = 262_144) -> tuple[np.ndarray, np.ndarray]:
        """Per-point best query (label) and its score.

        Args:
            queries: (L, D) label vectors.
        Returns:
            labels (N,) int64 index into the L queries (−1 for a point without a code), scores (N,) float32 (NaN
            for those).
        """
        labels, scores = [], []
        for _, s in self._blocks(queries, chunk):
            best = s.max(dim=0)
            labels.append(best.indices.cpu().numpy())
            scores.append(best.values.cpu().numpy())
        if not labels:
            return np.zeros(0, np.int64), np.zeros(0, np.float32)
        label, score = np.concatenate(labels).astype(np.int64), np.concatenate(scores)
        if self._absent is not None:
            absent = self._absent.cpu().numpy()
            label[absent], score[absent] = -1, np.nan
        return label, score
