"""Mapstore benchmark: ingest rate, memory per million points, query latency (p50/p99).

    .venv/bin/python bench/mapstore.py                 # full table (1M and 5M points, D = 384 and 768)
    .venv/bin/python bench/mapstore.py --points 1e6    # a subset

Ingest: synthetic keyframes at 384×512 (48×64 grid, K = 32) through the map core (fusion with
consistency against 2+2 neighbours), and through store + core (SQLite WAL, synchronous=FULL).
Query: top-k (k = 100) over N points for Q query vectors via the PCA identity (one (N, K+1) matrix).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import psutil
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from services.mapstore.config import MapParams  # noqa: E402
from services.mapstore.core.keyframe import KeyframeContent, KeyframeDepth  # noqa: E402
from services.mapstore.core.map import KeyframeMap  # noqa: E402
from services.mapstore.core.index import ScoringIndex  # noqa: E402
from services.mapstore.core.scoring import PcaBasis  # noqa: E402
from services.mapstore.store import MapStore  # noqa: E402

GRID_HW = (48, 64)
INTRINSICS = np.array([400.0, 400.0, 255.5, 191.5])


def synthetic_keyframe(rng: np.random.Generator, i: int, k: int) -> tuple[KeyframeContent, KeyframeDepth, np.ndarray]:
    h, w = GRID_HW
    v = np.linspace(-1, 1, h)[:, None]
    disp = (0.3 + 0.1 * v + 0.02 * rng.normal(size=(h, w))).astype(np.float32)  # a tilted wall, ~3 m
    content = KeyframeContent(i, i * 10**8, rng.normal(size=(h, w, k)).astype(np.float16),
                              rng.integers(0, 256, (h, w, 3), dtype=np.uint8), (8 * h, 8 * w), 1)
    pose = np.eye(4)
    pose[0, 3] = 0.05 * i
    return content, KeyframeDepth(disp, INTRINSICS, np.ones((h, w), np.float32), None), pose


def bench_ingest(n: int, k: int, with_store: bool) -> float:
    """Keyframes per second through (store +) map core, each keyframe fused at once."""
    rng = np.random.default_rng(0)
    frames = [synthetic_keyframe(rng, i, k) for i in range(n)]
    m = KeyframeMap(MapParams())
    with tempfile.TemporaryDirectory() as tmp:
        store = MapStore(Path(tmp) / "map.db") if with_store else None
        t0 = time.perf_counter()
        for content, depth, pose in frames:
            if store is not None:
                store.put_keyframe(content, INTRINSICS)
                store.put_graph({content.kf_id: pose}, {content.kf_id: depth})
            m.add_content(content)
            m.set_depth(content.kf_id, depth)
            m.set_pose(content.kf_id, pose)
            m.refresh()
        dt = time.perf_counter() - t0
        if store is not None:
            store.close()
    return n / dt


def bench_query(index: ScoringIndex, q: int, dim: int, reps: int) -> tuple[float, float]:
    rng = np.random.default_rng(1)
    queries = rng.normal(size=(q, dim)).astype(np.float32)
    index.topk(queries, 100)  # warm-up
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        index.topk(queries, 100)
        times.append(time.perf_counter() - t0)
    return float(np.percentile(times, 50) * 1e3), float(np.percentile(times, 99) * 1e3)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--points", type=float, nargs="+", default=[1e6, 5e6])
    ap.add_argument("--dims", type=int, nargs="+", default=[384, 768])
    ap.add_argument("--queries", type=int, nargs="+", default=[1, 10, 100])
    ap.add_argument("--k", type=int, default=32, help="PCA code size")
    ap.add_argument("--keyframes", type=int, default=60, help="keyframes for the ingest benchmark")
    ap.add_argument("--device", default="cpu")
    args = ap.parse_args()
    print(f"command: {' '.join(sys.argv)}")
    print(f"torch {torch.__version__}, threads {torch.get_num_threads()}, device {args.device}\n")

    core_rate = bench_ingest(args.keyframes, args.k, with_store=False)
    store_rate = bench_ingest(args.keyframes, args.k, with_store=True)
    print(f"| ingest (48x64 grid, K={args.k}) | keyframes/s |\n|---|---|")
    print(f"| map core (fusion + consistency) | {core_rate:.1f} |\n| store (SQLite FULL) + core | {store_rate:.1f} |\n")

    m = KeyframeMap(MapParams())
    rng = np.random.default_rng(2)
    proc = psutil.Process()
    rss0 = proc.memory_info().rss
    for i in range(args.keyframes):
        content, depth, pose = synthetic_keyframe(rng, i, args.k)
        m.add_content(content)
        m.set_depth(i, depth)
        m.set_pose(i, pose)
    m.refresh()
    fused = m.fused()
    n_kf_points = sum(len(m.keyframe_points(i).cells) for i in range(args.keyframes))
    rss_map = proc.memory_info().rss - rss0
    print(f"map of {args.keyframes} keyframes: {n_kf_points} keyframe points, {len(fused.keys)} voxels; "
          f"RSS growth {rss_map / 2**20:.0f} MiB = {rss_map / n_kf_points * 1e6 / 2**20:.0f} MiB per million "
          f"keyframe points (keyframe arrays + voxel accumulators + fused cache)\n")

    print("| points | D | Q | p50 ms | p99 ms | index MiB/M points |\n|---|---|---|---|---|---|")
    for n_points in (int(p) for p in args.points):
        codes = rng.normal(size=(n_points, args.k)).astype(np.float16)
        for dim in args.dims:
            basis = PcaBasis(1, rng.normal(size=dim).astype(np.float32),
                             np.linalg.qr(rng.normal(size=(dim, args.k)))[0].T.astype(np.float32))
            index = ScoringIndex(codes, basis, device=args.device)
            mib = index._a.element_size() * index._a.nelement() / 2**20 / (n_points / 1e6)
            for q in args.queries:
                reps = max(5, min(100, int(2e8 / (n_points * q))))
                p50, p99 = bench_query(index, q, dim, reps)
                print(f"| {n_points / 1e6:.0f}M | {dim} | {q} | {p50:.1f} | {p99:.1f} | {mib:.0f} |", flush=True)
            del index
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
