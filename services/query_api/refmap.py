"""A reference map queryable speaking the mapstore protocol (MapQuery → MapAnswer / MapSegment, MapChunk,
MapStats on ``kmvipe/<s>/map/**``), scoring by brute force in memory.

For tests, benchmarks and demos of the gateway without a mapstore; it is not durable and does no fusion.
Points carry PCA codes z (N, K) of a basis (μ (D,), V (K, D)); cos(μ + Vᵀz, t) is evaluated as one matrix
product with precomputed per-point terms (the same identity the mapstore uses).
"""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import numpy as np
import torch

from ..common import keys
from ..common.bus import Bus
from ..common.errors import UnknownSession
from ..common.schema import MapAnswer, MapChunk, MapQuery, MapSegment, MapSessions, MapStats, decode


@dataclass(frozen=True)
class RefMapParams:
    """How the reference map forms regions."""

    voxel_size: float = 0.1
    """Edge of the voxels whose 26-connected components are the regions (map units)."""
    relative_threshold: float = 0.8
    """With no threshold in the query, points scoring at least this fraction of the best score take part."""
    min_points: int = 3
    """Components with fewer points are dropped as noise."""
    chunk_points: int = 100_000
    """Default export chunk size."""


def connected_voxels(ijk: np.ndarray) -> np.ndarray:
    """(M, 3) int64 voxel indices → (M,) component labels (26-connectivity), labels in [0, C)."""
    m = len(ijk)
    if m == 0:
        return np.zeros(0, np.int64)
    lo = ijk.min(axis=0) - 1
    span = ijk.max(axis=0) - lo + 2
    code = lambda v: ((v[:, 0] - lo[0]) * span[1] + (v[:, 1] - lo[1])) * span[2] + (v[:, 2] - lo[2])  # noqa: E731
    own = code(ijk)
    order = np.argsort(own)
    sorted_codes = own[order]
    src, dst = [], []
    for off in [(a, b, c) for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1) if (a, b, c) > (0, 0, 0)]:
        nb = code(ijk + np.array(off))
        pos = np.clip(np.searchsorted(sorted_codes, nb), 0, m - 1)
        hit = sorted_codes[pos] == nb
        src.append(np.flatnonzero(hit))
        dst.append(order[pos[hit]])
    src, dst = np.concatenate(src), np.concatenate(dst)
    label = np.arange(m)
    while True:  # min-label propagation with pointer jumping
        low = np.minimum(label[src], label[dst])
        new = label.copy()
        np.minimum.at(new, src, low)
        np.minimum.at(new, dst, low)
        new = new[new]
        if np.array_equal(new, label):
            break
        label = new
    return np.unique(label, return_inverse=True)[1]


class RefMap:
    """Points xyz (N, 3) float32, rgb (N, 3) uint8 and PCA codes (N, K) of basis ``mean`` (D,) /
    ``components`` (K, D) in backbone space ``backbone``."""

    def __init__(self, xyz, rgb, codes, mean, components, backbone: str, params: RefMapParams = RefMapParams(),
                 device: str = "cpu"):
        n = len(xyz)
        if np.shape(xyz) != (n, 3) or np.shape(rgb) != (n, 3) or np.ndim(codes) != 2 or len(codes) != n:
            raise ValueError(f"need xyz (N, 3), rgb (N, 3), codes (N, K); got {np.shape(xyz)}, {np.shape(rgb)}, {np.shape(codes)}")
        if np.shape(components) != (np.shape(codes)[1], np.shape(mean)[0]):
            raise ValueError(f"components must be (K, D) = {(np.shape(codes)[1], np.shape(mean)[0])}, got {np.shape(components)}")
        self.xyz, self.rgb = np.asarray(xyz, np.float32), np.asarray(rgb, np.uint8)
        self.codes = np.asarray(codes, np.float16)
        self.backbone, self.params = backbone, params
        self.lock = threading.Lock()
        z, v, mu = np.asarray(codes, np.float64), np.asarray(components, np.float64), np.asarray(mean, np.float64)
        norm2 = mu @ mu + 2.0 * z @ (v @ mu) + np.einsum("nk,kl,nl->n", z, v @ v.T, z)
        inv = 1.0 / np.sqrt(np.maximum(norm2, 1e-12))
        self._a = torch.from_numpy(np.concatenate([z * inv[:, None], inv[:, None]], 1).astype(np.float32)).to(device)
        self._v = torch.from_numpy(v.astype(np.float32)).to(device)
        self._mu = torch.from_numpy(mu.astype(np.float32)).to(device)
        self.ijk = np.floor(self.xyz / params.voxel_size).astype(np.int64)
        lo = self.ijk.min(axis=0) if n else np.zeros(3, np.int64)
        span = self.ijk.max(axis=0) - lo + 1 if n else np.ones(3, np.int64)
        self._voxel_key = ((self.ijk[:, 0] - lo[0]) * span[1] + (self.ijk[:, 1] - lo[1])) * span[2] + (self.ijk[:, 2] - lo[2])
        self.n_voxels = len(np.unique(self._voxel_key))

    @property
    def dim(self) -> int:
        return int(self._mu.shape[0])

    def score(self, vectors: np.ndarray) -> np.ndarray:
        """(Q, D) float32 → (Q, N) float32 cosine scores."""
        t = torch.from_numpy(np.array(vectors, np.float32)).to(self._a.device)
        if t.ndim != 2 or t.shape[1] != self.dim:
            raise ValueError(f"query vectors must be (Q, {self.dim}), got {tuple(t.shape)}")
        b = torch.cat([t @ self._v.T, (t @ self._mu)[:, None]], 1) / t.norm(dim=1, keepdim=True).clamp_min(1e-12)
        return (b @ self._a.T).cpu().numpy()

    def _check_space(self, q: MapQuery) -> None:
        if q.space and q.space != self.backbone:
            raise ValueError(f"query vectors are in '{q.space}' but this map is in '{self.backbone}'")

    def query(self, q: MapQuery) -> MapAnswer:
        self._check_space(q)
        scores = self.score(q.vectors)
        rq, rs, rc, rmin, rmax, rn, pq, pxyz, ps = ([] for _ in range(9))
        for qi, s in enumerate(scores):
            k = min(q.top_k, len(s))
            top = np.argpartition(-s, k - 1)[:k] if k else np.zeros(0, np.int64)
            top = top[np.argsort(-s[top], kind="stable")]
            pq += [qi] * k
            pxyz.append(self.xyz[top])
            ps.append(s[top])
            for reg in self._regions(s, q.threshold)[: q.max_regions]:
                rq.append(qi)
                for lst, val in zip((rs, rc, rmin, rmax, rn), reg):
                    lst.append(val)
        f4 = lambda x, shape: np.asarray(x, np.float32).reshape(shape)  # noqa: E731
        return MapAnswer(q.stream, q.seq, time.time_ns(), region_query=np.asarray(rq, np.int32),
                         region_score=f4(rs, (-1,)), region_centroid=f4(rc, (-1, 3)), region_box_min=f4(rmin, (-1, 3)),
                         region_box_max=f4(rmax, (-1, 3)), region_count=np.asarray(rn, np.int32),
                         point_query=np.asarray(pq, np.int32), point_xyz=f4(np.concatenate(pxyz) if pxyz else [], (-1, 3)),
                         point_score=f4(np.concatenate(ps) if ps else [], (-1,)),
                         all_scores=scores.astype(np.float32) if q.with_points else None, n_points=len(self.xyz))

    def _regions(self, s: np.ndarray, threshold: float) -> list[tuple]:
        if not len(s):
            return []
        thr = threshold if threshold >= 0 else self.params.relative_threshold * float(s.max())
        sel = np.flatnonzero(s >= thr)
        _, first, inverse = np.unique(self._voxel_key[sel], return_index=True, return_inverse=True)
        comp = connected_voxels(self.ijk[sel[first]])[inverse.ravel()]
        out = []
        for c in range(int(comp.max()) + 1 if len(comp) else 0):
            idx = sel[comp == c]
            if len(idx) >= self.params.min_points:
                p = self.xyz[idx]
                out.append((float(s[idx].mean()), p.mean(0), p.min(0), p.max(0), len(idx)))
        return sorted(out, key=lambda r: -r[0])

    def segment(self, q: MapQuery) -> MapSegment:
        self._check_space(q)
        scores = self.score(q.vectors)
        return MapSegment(q.stream, q.seq, time.time_ns(), xyz=self.xyz, label=scores.argmax(0).astype(np.int32),
                          score=scores.max(0).astype(np.float32))

    def export(self, stream: str, chunk: int, size: int) -> MapChunk:
        n = len(self.xyz)
        sl = slice(chunk * size, (chunk + 1) * size)
        return MapChunk(stream, chunk, time.time_ns(), xyz=self.xyz[sl], rgb=self.rgb[sl], codes=self.codes[sl],
                        n_chunks=max(1, -(-n // size)), total_points=n)

    def stats(self, stream: str) -> MapStats:
        return MapStats(stream, 0, time.time_ns(), keyframes=0, points=len(self.xyz), voxels=self.n_voxels,
                        backbone=self.backbone, pca_version=1)

    def handle(self, stream: str, key: str, params: dict, payload: bytes | None) -> bytes:
        """The queryable handler (``Bus.serve``)."""
        verb = key.rsplit("/", 1)[-1]
        if verb == "sessions":  # one map, outside any session
            return MapSessions(stream, 0, 0, current="", names="", keyframes=np.zeros(0, np.int64),
                               finished=np.zeros(0, np.uint8)).encode()
        if params.get("session"):
            raise UnknownSession(f"stream {stream!r} has no map of session {params['session']!r}; this map has "
                                 "no sessions")
        with self.lock:
            if verb in ("query", "segment"):
                q = decode(payload or b"", MapQuery)
                return (self.query(q) if verb == "query" else self.segment(q)).encode()
            if verb == "export":
                return self.export(stream, int(params.get("chunk", 0)), int(params.get("chunk_size", self.params.chunk_points))).encode()
            if verb == "stats":
                return self.stats(stream).encode()
        raise KeyError(f"unknown map verb {verb!r}")

    def serve(self, bus: Bus, stream: str) -> None:
        """Answer ``kmvipe/<stream>/map/**`` on ``bus``."""
        bus.serve(keys.map_key(stream, "**"), lambda key, params, payload: self.handle(stream, key, params, payload))
