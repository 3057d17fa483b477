"""``kmvipe query "chair" [--stream s] [--url http://127.0.0.1:8000]``: ask a running gateway, print a table."""
from __future__ import annotations

import argparse
import os
import sys

import httpx

from ..common.keys import DEFAULT_STREAM

DEFAULT_URL = "http://127.0.0.1:8000"


def register(subparsers) -> None:
    p = subparsers.add_parser("query", help="ask a running query gateway where things are")
    p.add_argument("texts", nargs="+", help="one or more texts, e.g. chair 'fire extinguisher'")
    p.add_argument("--stream", default=DEFAULT_STREAM, help="stream name")
    p.add_argument("--url", default=os.environ.get("KMVIPE_QUERY_URL", DEFAULT_URL), help="gateway base URL")
    p.add_argument("--top-k", type=int, default=5, help="top points per text")
    p.add_argument("--regions", type=int, default=5, help="most regions per text")
    p.add_argument("--api-key", default=os.environ.get("KMVIPE_QUERY_API_KEY", ""), help="X-API-Key (if required)")
    p.add_argument("--timeout", type=float, default=30.0, help="seconds to wait for the answer")
    p.set_defaults(func=_cmd_query)


def _cmd_query(args: argparse.Namespace) -> int:
    headers = {"X-API-Key": args.api_key} if args.api_key else {}
    body = {"texts": args.texts, "top_k": args.top_k, "max_regions": args.regions}
    url = f"{args.url.rstrip('/')}/v1/streams/{args.stream}/query"
    try:
        res = httpx.post(url, json=body, headers=headers, timeout=args.timeout)
    except httpx.HTTPError as exc:
        print(f"kmvipe query: cannot reach the gateway at {args.url} ({exc}); is 'kmvipe service query_api' running?",
              file=sys.stderr)
        return 2
    if res.status_code != 200:
        detail = res.json().get("detail", res.text) if res.headers.get("content-type", "").startswith("application/json") else res.text
        print(f"kmvipe query: {res.status_code}: {detail}", file=sys.stderr)
        return 1
    print(format_answer(res.json()))
    return 0


def format_answer(answer: dict) -> str:
    """A readable table of a QueryResponse (JSON dict)."""
    lines = [f"stream {answer['stream']}: {answer['n_points']} points (space {answer['space']})", ""]
    header = f"{'text':<22} {'#':>2} {'score':>6} {'points':>7}  {'centre (x, y, z)':<26} {'box size':<20}"
    lines += [header, "-" * len(header)]
    for res in answer["results"]:
        if not res["regions"]:
            lines.append(f"{res['text'][:22]:<22}  -  (no region above the threshold)")
        for i, r in enumerate(res["regions"]):
            centre = ", ".join(f"{v:.2f}" for v in r["centroid"])
            size = " x ".join(f"{hi - lo:.2f}" for lo, hi in zip(r["box_min"], r["box_max"]))
            name = res["text"][:22] if i == 0 else ""
            lines.append(f"{name:<22} {i + 1:>2} {r['score']:>6.3f} {r['count']:>7}  ({centre:<24}) {size:<20}")
    return "\n".join(lines)
