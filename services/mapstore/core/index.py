"""The scoring index: every point's precomputed terms on the scoring device, and cosine scores, top k and argmax
of query vectors against them (the formulas: :mod:`services.mapstore.core.scoring`). Torch, so that a CUDA device
scores when there is one."""
from __future__ import annotations

import numpy as np
import torch

from services.common.device import resolve_device
from services.mapstore.core.scoring import EPS, PcaBasis, TopK


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
        inv = 1.0 / np.sqrt(np.maximum(norm2, EPS))
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
        return b / t.norm(dim=1, keepdim=True).clamp_min(EPS)

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
