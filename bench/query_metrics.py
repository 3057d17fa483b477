"""The metric core of bench/query_example.py (no model, no data files): grid cells labelled by their pixels'
majority, the map scored as the product scores it (PCA codes through the mapstore's ``ScoringIndex``), and
precision / recall / F1 at the product's threshold, at the best threshold per query and at one oracle-tuned
threshold for all. tests/test_bench_query_example.py checks it on cases with a known answer."""
from __future__ import annotations

from typing import Callable, NamedTuple

import numpy as np

from services.features.core.pca import fit_pca, project, sample_rows
from services.mapstore.config import RegionParams
from services.mapstore.core.index import ScoringIndex
from services.mapstore.core.scoring import PcaBasis

PCA_K, PCA_SAMPLES = 32, 4096  # the features service's PcaParams defaults
SWEEP = np.round(np.arange(0.0, 1.0001, 0.01), 2)  # thresholds tried for the oracle-tuned global threshold


# -- metric core --------------------------------------------------------------------------------------------
def cell_majority(labels: np.ndarray, grid: tuple[int, int]) -> np.ndarray:
    """(H, W) integer labels → (h, w) int64 most frequent label of the pixels whose centre falls in each cell.

    Cell (i, j) of an h×w grid over the image holds the pixels with ⌊(y + ½)·h/H⌋ = i and ⌊(x + ½)·w/W⌋ = j
    (the 1/8 grid of the working image, mapped back to the original). Ties go to the smaller label.
    """
    H, W = labels.shape
    h, w = grid
    values, inverse = np.unique(labels, return_inverse=True)
    rows = ((np.arange(H) + 0.5) * h / H).astype(np.int64)
    cols = ((np.arange(W) + 0.5) * w / W).astype(np.int64)
    cell = (rows[:, None] * w + cols[None, :]).ravel()
    counts = np.bincount(cell * len(values) + inverse.ravel(), minlength=h * w * len(values))
    return values[counts.reshape(h * w, len(values)).argmax(1)].reshape(h, w).astype(np.int64)


class Prf(NamedTuple):
    precision: float  # 0 when nothing is retrieved
    recall: float
    f1: float
    retrieved: int


def prf(retrieved: np.ndarray, relevant: np.ndarray) -> Prf:
    """Precision, recall, F1 of (N,) bool retrieved cells against (N,) bool relevant ones (at least one)."""
    tp, n_ret, n_rel = int((retrieved & relevant).sum()), int(retrieved.sum()), int(relevant.sum())
    p, r = (tp / n_ret if n_ret else 0.0), tp / n_rel
    return Prf(p, r, 2 * p * r / (p + r) if p + r else 0.0, n_ret)


def product_threshold(map_scores: np.ndarray, params: RegionParams = RegionParams()) -> float:
    """The mapstore's region threshold for a query that names none (services/mapstore/queries.py ``_threshold``)."""
    scored = map_scores[np.isfinite(map_scores)]
    if params.relative_threshold > 0 and scored.size:
        return params.relative_threshold * float(scored.max())
    return params.score_threshold


def best_f1_threshold(scores: np.ndarray, relevant: np.ndarray) -> tuple[float, float]:
    """Oracle: the threshold (one of the scores) that maximises F1 of ``scores >= t``, and that F1."""
    order = np.argsort(-scores, kind="stable")
    s, tp = scores[order], np.cumsum(relevant[order])
    last = np.r_[s[1:] != s[:-1], True]  # only cut between different scores
    k = np.arange(1, len(s) + 1)
    f1 = np.where(last, 2 * tp / (k + relevant.sum()), -1.0)
    i = int(f1.argmax())
    return float(s[i]), float(f1[i])


class Frame(NamedTuple):
    """One frame of the map. ``features``: (C, h, w) unit features on the 1/8 grid; ``cells``: (h, w) int64 ground
    truth id per cell; ``in_map``: (h, w) bool cells that are map points; ``counted``: (h, w) bool cells scored."""

    name: str
    features: np.ndarray
    cells: np.ndarray
    in_map: np.ndarray
    counted: np.ndarray


class Query(NamedTuple):
    frame: int  # index of the query frame
    target: int  # ground-truth id queried
    group: str  # its category / class
    kind: str  # "box" or "mask"
    vector: np.ndarray  # (C,) pooled unit feature
    region: str  # the labelled region the query was made from


def map_scorer(frames: list[Frame], mode: str) -> Callable[[np.ndarray], np.ndarray]:
    """(Q, C) query vectors → (Q, N) scores of every cell of every frame (frames concatenated, row-major), NaN for
    cells that are no map points. ``mode="pca"``: the product's path (K-d PCA basis fitted on the map cells, float16
    codes, ``ScoringIndex``); ``"raw"``: cosine with the full features (what PCA costs); ``"centred"``: NOT the
    product, a diagnostic: cosine of the codes z = V(f − μ) with V(t − μ) (PCA mean μ removed on both sides)."""
    rows = np.concatenate([f.features.reshape(f.features.shape[0], -1).T for f in frames])  # (N, C)
    in_map = np.concatenate([f.in_map.ravel() for f in frames])
    if mode == "raw":
        feats = rows / np.linalg.norm(rows, axis=1, keepdims=True).clip(1e-12)
        return lambda q: np.where(in_map[None], np.asarray(q, np.float32) @ feats.T, np.nan)
    gen = np.random.default_rng(0)
    samples = np.concatenate([sample_rows(f.features.reshape(f.features.shape[0], -1)[:, f.in_map.ravel()].T,
                                     PCA_SAMPLES, gen) for f in frames])
    basis = fit_pca(samples, min(PCA_K, rows.shape[1]), "bench")
    codes = np.concatenate([project(basis, f.features).reshape(-1, basis.components.shape[0]) for f in frames])
    if mode == "centred":
        unit = lambda x: x / np.linalg.norm(x, axis=1, keepdims=True).clip(1e-12)  # noqa: E731
        z = unit(codes.astype(np.float32))
        return lambda q: np.where(in_map[None], unit((np.asarray(q, np.float32) - basis.mean) @ basis.components.T)
                                  @ z.T, np.nan)
    index = ScoringIndex(codes, PcaBasis(basis.version, basis.mean, basis.components, "bench"), "cpu", in_map)
    return index.score


def evaluate(frames: list[Frame], queries: list[Query], group_of: dict[int, str], mode: str = "pca",
             params: RegionParams = RegionParams()) -> list[dict]:
    """Per query: P/R/F1 on the other frames' counted cells at the product's threshold, the fixed
    ``params.score_threshold`` and the oracle per-query threshold (``scores``/``relevant`` kept for a sweep)."""
    if not queries:  # nothing to score
        return []
    scores = map_scorer(frames, mode)(np.stack([q.vector for q in queries]))
    frame_of = np.concatenate([np.full(f.cells.size, i) for i, f in enumerate(frames)])
    cells = np.concatenate([f.cells.ravel() for f in frames])
    counted = np.concatenate([f.counted.ravel() for f in frames])
    groups = np.array([group_of.get(int(c), "") for c in cells])
    out = []
    for q, s in zip(queries, scores):
        sel = counted & (frame_of != q.frame)
        rel, rel_group = cells[sel] == q.target, groups[sel] == q.group
        if not rel.any():
            continue
        t_prod = product_threshold(s, params)
        ret = s[sel] >= t_prod
        out.append({"frame": frames[q.frame].name, "region": q.region, "group": q.group, "kind": q.kind,
                    "base_rate": float(rel.mean()), "threshold": t_prod, "product": prf(ret, rel)._asdict(),
                    "product_group": prf(ret, rel_group)._asdict(),
                    "fixed": prf(s[sel] >= params.score_threshold, rel)._asdict(),
                    "oracle_query": dict(zip(("threshold", "f1"), best_f1_threshold(s[sel], rel))),
                    "oracle_query_group": dict(zip(("threshold", "f1"), best_f1_threshold(s[sel], rel_group))),
                    "scores": s[sel], "relevant": rel})
    return out


def global_oracle(rows: list[dict], thresholds: np.ndarray = SWEEP) -> tuple[float, list[Prf]]:
    """Oracle: the one threshold of ``thresholds`` with the best mean F1 over ``rows``, and each row's P/R/F1 there."""
    best_t, best = float(thresholds[0]), None
    for t in thresholds:
        res = [prf(r["scores"] >= t, r["relevant"]) for r in rows]
        if best is None or np.mean([x.f1 for x in res]) > np.mean([x.f1 for x in best]):
            best_t, best = float(t), res
    return best_t, best or []
