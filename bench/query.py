"""Query gateway benchmark: HTTP query latency (p50/p99) with a cached text embedding, over a 1M-point map.

    .venv/bin/python bench/query.py                        # 1M points, the real mapstore query code, 1 and 16 clients
    .venv/bin/python bench/query.py --answer-cache off     # every request scored (no answer reused)
    .venv/bin/python bench/query.py --map ref --points 2e5  # the gateway's reference (brute-force) queryable

One child process serves the map (``--map mapstore``: services.mapstore.queries on a prebuilt fused map —
scoring index, top-k and region clustering exactly as the mapstore runs them; ``--map ref``:
services.query_api.refmap) and the gateway (uvicorn + the oracle text encoder, so the text embedding is
cached after the warm-up) on a loopback Zenoh bus. The parent sends ``POST /v1/streams/<s>/query`` with one
text from 1 and 16 concurrent clients and reports p50/p99 of the wall-clock latency per request; before that,
the same query straight on the bus (``zenoh``: the map's share) and, with ``--map mapstore``, in this process
(``inproc``: services.mapstore.queries.query on the same map, no transport). The mapstore answers a repeated
request on an unchanged map from its answer cache; ``--answer-cache off`` makes it score every request (the
cost of a query on a map that changed since the last one). The load average is printed with the results.
Map: N unique voxels (0.02 m) in a 4 × 4 × 2 m volume, one of ``--labels`` labels per 0.5 m block, PCA codes (K = 32) of
oracle features (D = 768) with noise.
"""
from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

STREAM, D, K, VOXEL = "bench", 768, 32, 0.02
LABELS = ("floor", "wall", "ceiling", "door", "table", "chair", "shelf", "cabinet", "sofa", "monitor",
          "fire extinguisher", "plant", "person")


def label_names(n_labels: int) -> tuple[str, ...]:
    """The synthetic world's label names, then ``object_<i>`` up to ``n_labels``."""
    return (LABELS + tuple(f"object_{i}" for i in range(len(LABELS), n_labels)))[:n_labels]


def build_map(n: int, n_labels: int = len(LABELS), seed: int = 0):
    """xyz (N, 3) f4, rgb (N, 3) u1, codes (N, K) f4, basis mean (D,), components (K, D), label vectors (L, D)."""
    rng = np.random.default_rng(seed)
    dims = np.array([200, 200, 100])
    flat = rng.choice(int(np.prod(dims)), size=n, replace=False)
    ijk = np.stack(np.unravel_index(flat, dims), 1).astype(np.int64)
    xyz = ((ijk + 0.5) * VOXEL).astype(np.float32)
    block = (ijk // 25)  # 0.5 m blocks
    label = (block[:, 0] * 7 + block[:, 1] * 3 + block[:, 2] * 11) % n_labels
    space_rng = np.random.default_rng([seed, 1])  # basis and label vectors do not depend on n
    comps = np.linalg.qr(space_rng.normal(size=(D, K)))[0].T.astype(np.float32)  # (K, D) orthonormal rows
    vecs = space_rng.normal(size=(n_labels, K)) @ comps  # label vectors inside the PCA span
    vecs = (vecs / np.linalg.norm(vecs, axis=1, keepdims=True)).astype(np.float32)
    codes = (vecs[label] @ comps.T + 0.3 * rng.normal(size=(n, K)) / np.sqrt(K)).astype(np.float32)
    rgb = rng.integers(0, 256, (n, 3)).astype(np.uint8)
    return ijk, xyz, rgb, codes, np.zeros(D, np.float32), comps, vecs


class _FusedMap:
    """What services.mapstore.queries reads of ``MapState.map``."""

    def __init__(self, fused, params):
        self._fused, self.params, self.revision, self.contents = fused, params, 1, {}

    def fused(self):
        return self._fused


class _MapState:
    """What services.mapstore.queries reads of ``MapState``: a prebuilt fused map and its scoring index."""

    def __init__(self, ijk, xyz, rgb, codes, basis, answer_cache: int):
        from services.mapstore.config import MapParams
        from services.mapstore.core.fusion import FusedVoxels
        from services.mapstore.core.index import ScoringIndex
        from services.mapstore.answer_cache import AnswerCache

        n = len(xyz)
        fused = FusedVoxels(np.arange(n, dtype=np.int64), ijk, xyz.astype(np.float64), codes, rgb, np.ones(n), np.ones(n, np.int64))
        self.lock, self.map, self.bases, self.metric = threading.RLock(), _FusedMap(fused, MapParams()), {1: basis}, True
        self.session = ""
        self._index = ScoringIndex(codes, basis, "cpu")
        self.answers = AnswerCache(answer_cache)

    def index(self):
        return self._index

    def keyframe_count(self) -> int:
        return 1

    def without_codes_count(self) -> int:
        return 0


def serve(args, port_queue) -> None:
    """Child process: map queryable + gateway; puts the HTTP port on ``port_queue``, runs until killed."""
    from services.common.bus import Bus
    from services.common.config import BusSettings
    from services.query_api.config import QuerySettings
    from services.query_api.core.text import OracleTextEncoder, TextEmbedder
    from services.query_api.gateway import Gateway
    from services.query_api.service import start_background
    from services.query_api.textpath import TextPath

    ijk, xyz, rgb, codes, mean, comps, vecs = build_map(args.points, args.labels)
    endpoint = f"tcp/127.0.0.1:{args.zenoh_port}"
    map_bus = Bus(BusSettings(mode="peer", listen=[endpoint]), "mapstore")
    if args.map == "mapstore":
        from services.mapstore import queries
        from services.mapstore.core.scoring import PcaBasis

        state = _MapState(ijk, xyz, rgb, codes, PcaBasis(1, mean, comps, "oracle"), _answer_cache(args))
        map_bus.serve(f"kmvipe/{STREAM}/map/**", lambda key, p, payload: queries.answer(state, STREAM, key, p, payload))
    else:
        from services.query_api.refmap import RefMap, RefMapParams

        RefMap(xyz, rgb, codes, mean, comps, "oracle", RefMapParams(voxel_size=VOXEL * 1.01)).serve(map_bus, STREAM)
    gw_bus = Bus(BusSettings(mode="peer", connect=[endpoint]), "query_api")
    cfg = QuerySettings(_env_file=None, text_encoder="oracle", port=0, timeout_s=30.0)
    gw = Gateway(cfg, gw_bus, text=TextPath(cfg, TextEmbedder(OracleTextEncoder(label_names(args.labels), vecs, "oracle"))))
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        try:
            gw.maps.stats(STREAM)
            break
        except Exception:  # noqa: BLE001 - the bus is still connecting
            time.sleep(0.05)
    _, thread, port = start_background(cfg, gw_bus, gw)
    port_queue.put(port)
    thread.join()


def run_clients(url: str, clients: int, requests: int, text: str) -> np.ndarray:
    """Latencies (s) of ``requests`` queries per client from ``clients`` threads."""
    import httpx

    body = {"texts": [text], "top_k": 20, "max_regions": 10}

    def one_client(_):
        out = []
        with httpx.Client(timeout=60) as http:
            for _ in range(requests):
                t0 = time.perf_counter()
                res = http.post(f"{url}/v1/streams/{STREAM}/query", json=body)
                out.append(time.perf_counter() - t0)
                if res.status_code != 200:
                    raise RuntimeError(f"{res.status_code}: {res.text}")
        return out

    with ThreadPoolExecutor(clients) as pool:
        return np.concatenate([np.array(x) for x in pool.map(one_client, range(clients))])


def run_direct(args, requests: int) -> np.ndarray:
    """Latencies (s) of the same query asked straight on the bus (no HTTP): the map's share of the latency."""
    from services.common.bus import Bus
    from services.common.config import BusSettings
    from services.query_api.mapclient import MapClient, QueryOptions

    vec = build_map(1000, args.labels)[-1][label_names(args.labels).index(args.text)][None]  # seed-only vectors
    with Bus(BusSettings(mode="peer", connect=[f"tcp/127.0.0.1:{args.zenoh_port}"]), "bench") as bus:
        client = MapClient(bus, 60.0)
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            try:
                client.stats(STREAM)
                break
            except Exception:  # noqa: BLE001 - still connecting
                time.sleep(0.05)
        out = []
        for _ in range(requests):
            t0 = time.perf_counter()
            client.query(STREAM, vec, "oracle", QueryOptions(top_k=20, max_regions=10))
            out.append(time.perf_counter() - t0)
    return np.array(out)


def run_inproc(args, requests: int) -> np.ndarray:
    """Latencies (s) of the same query as services.mapstore.queries.query in this process (no bus, no HTTP)."""
    from services.common.schema import MapQuery
    from services.mapstore import queries
    from services.mapstore.core.scoring import PcaBasis

    ijk, xyz, rgb, codes, mean, comps, vecs = build_map(args.points, args.labels)
    state = _MapState(ijk, xyz, rgb, codes, PcaBasis(1, mean, comps, "oracle"), _answer_cache(args))
    vec = vecs[label_names(args.labels).index(args.text)][None]
    out = []
    for i in range(requests + 5):  # the first 5: warm-up (first touch of the index, answer cached)
        t0 = time.perf_counter()
        with state.lock:
            queries.query(state, MapQuery(STREAM, i, time.time_ns(), vectors=vec, space="oracle", top_k=20,
                                          max_regions=10))
        out.append(time.perf_counter() - t0)
    return np.array(out[5:])


def _answer_cache(args) -> int:
    """The mapstore's answer cache size for ``--answer-cache`` (its default, or 0: every request scored)."""
    from services.mapstore.config import MapstoreSettings

    return MapstoreSettings.model_fields["answer_cache"].default if args.answer_cache == "on" else 0


def _row(args, route: str, clients: int, lat: np.ndarray, wall: float) -> dict:
    return {"map": args.map, "labels": args.labels, "text": args.text, "answer_cache": args.answer_cache,
            "route": route, "points": args.points, "clients": clients, "requests": len(lat),
            "p50_ms": 1e3 * float(np.percentile(lat, 50)), "p99_ms": 1e3 * float(np.percentile(lat, 99)),
            "throughput_qps": len(lat) / wall}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--points", type=float, default=1e6)
    ap.add_argument("--map", choices=["mapstore", "ref"], default="mapstore")
    ap.add_argument("--requests", type=int, default=100, help="requests per client")
    ap.add_argument("--clients", type=int, nargs="+", default=[1, 16])
    ap.add_argument("--text", default="chair")
    ap.add_argument("--labels", type=int, default=len(LABELS),
                    help="labels in the map (each covers about 1/labels of the points; 13: chair ≈ 7.7%%)")
    ap.add_argument("--answer-cache", choices=["on", "off"], default="on",
                    help="off: the mapstore scores every request (no answer reused on the unchanged map)")
    ap.add_argument("--inproc", action=argparse.BooleanOptionalAction, default=True,
                    help="also time the mapstore query in this process (--map mapstore only)")
    ap.add_argument("--zenoh-port", type=int, default=17650)
    ap.add_argument("--json", type=Path, help="also write the results here")
    args = ap.parse_args()
    args.points = int(args.points)
    ctx = mp.get_context("spawn")
    ports = ctx.Queue()
    child = ctx.Process(target=serve, args=(args, ports), daemon=True)
    child.start()
    try:
        url = f"http://127.0.0.1:{ports.get(timeout=600)}"  # the child is idle from here on
        rows, load = [], [round(x, 2) for x in os.getloadavg()]
        if args.inproc and args.map == "mapstore":
            lat = run_inproc(args, args.requests)
            rows.append(_row(args, "inproc", 1, lat, float(lat.sum())))  # wall: the queries, not the map build
        run_clients(url, 1, 5, args.text)  # warm-up: embedding cached, index built, sockets open
        t0 = time.perf_counter()
        lat = run_direct(args, args.requests)
        rows.append(_row(args, "zenoh", 1, lat, time.perf_counter() - t0))
        for clients in args.clients:
            per_client = max(1, args.requests // clients) if clients > 1 else args.requests
            t0 = time.perf_counter()
            lat = run_clients(url, clients, per_client, args.text)
            rows.append(_row(args, "http", clients, lat, time.perf_counter() - t0))
        load += [round(x, 2) for x in os.getloadavg()]
        for r in rows:
            r["loadavg_1_5_15_before_after"] = load
        print(f"text {args.text!r}, {args.labels} labels, answer cache {args.answer_cache}; load average (1, 5, 15 min) "
              f"before {load[:3]}, after {load[3:]}")
        print(f"{'map':<9} {'route':<6} {'points':>9} {'clients':>7} {'requests':>8} {'p50 ms':>8} {'p99 ms':>8} {'q/s':>7}")
        for r in rows:
            print(f"{r['map']:<9} {r['route']:<6} {r['points']:>9} {r['clients']:>7} {r['requests']:>8} "
                  f"{r['p50_ms']:>8.2f} {r['p99_ms']:>8.2f} {r['throughput_qps']:>7.1f}")
        if args.json:
            args.json.write_text(json.dumps(rows, indent=2))
    finally:
        child.kill()
        child.join(5)


if __name__ == "__main__":
    main()
