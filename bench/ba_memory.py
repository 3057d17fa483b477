"""Benchmark: peak memory and time of an end-of-stream-sized BA, Jacobians formed all at once or in edge slices.

The ba service's end-of-stream BA runs over every held keyframe (up to ``keep_keyframes``, 100): hundreds of edges
whose per-pixel Jacobians and their intermediates were ~1 GB at once. ``BAParams.linearise_edges`` forms them a
slice of edges at a time. Each variant runs in a fresh process (peak RSS is a process's high-water mark): a
synthetic window of ``--keyframes`` on the ``--grid`` with the service's global-BA parameters, ARK codes on, and
``--iters`` LM iterations from a perturbed start.

``--allocators glibc,tcmalloc`` runs each variant on each C allocator (services/common/allocator.py; TCMalloc
preloaded into the variant's process) and ``--repeat N`` runs the same BA N times in that process, as ba runs one
background BA after another: the first pays for fresh pages, the later ones show what the allocator reuses.

Usage: ``python bench/ba_memory.py [--keyframes 100] [--radius 3] [--grid 48x64] [--slices 0,96,32] [--iters 3]
[--allocators glibc] [--repeat 1]``
Prints a markdown table: allocator, edges, slice, peak RSS over the process's RSS before the BA, RSS after the
last BA, seconds (the first BA; the median of the later ones), final cost.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import psutil
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # run from any directory
from services.ba.core import ba, synthetic  # noqa: E402
from services.ba.settings import BaSettings  # noqa: E402
from services.common import allocator  # noqa: E402
from services.common.lifecycle import tune_malloc_for_tensors  # noqa: E402


def one(keyframes: int, radius: int, h: int, w: int, slices: int, iters: int, repeat: int = 1) -> dict:
    """``repeat`` times the same BA in this process: its figures."""
    torch.set_num_threads(1)
    tune_malloc_for_tensors()  # as the ba service
    win = synthetic.make_window(n=keyframes, h=h, w=w, focal=0.55 * w, radius=radius, seed=0)
    gen = torch.Generator().manual_seed(1)
    codes = torch.randn(keyframes, h, w, 32, generator=gen)  # ARK samples them: the service's global BA has codes
    codes = codes.permute(0, 3, 1, 2).contiguous().permute(0, 2, 3, 1)  # stored channels first, as graph.run does
    problem = win.problem._replace(codes=codes)
    start = ba.BAState(synthetic.perturb_poses(win.truth.poses, 0.01, 0.5, gen), win.truth.disparity * 1.1,
                       win.truth.intrinsics)
    params = replace(BaSettings().ba_params(global_ba=True), iterations=iters, linearise_edges=slices)
    before = psutil.Process().memory_info().rss
    seconds = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        res = ba.run_ba(start, problem, params)
        seconds.append(time.perf_counter() - t0)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # Linux: KiB
    return {"edges": len(problem.ii), "slices": slices, "peak_mb": (peak - before) / 1e6, "seconds": seconds[0],
            "later_s": statistics.median(seconds[1:]) if repeat > 1 else None, "allocator": allocator.in_use(),
            "after_mb": psutil.Process().memory_info().rss / 1e6, "cost": res.costs[-1],
            "iterations": len(res.costs) - 1}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--keyframes", type=int, default=100)
    parser.add_argument("--radius", type=int, default=3)
    parser.add_argument("--grid", default="48x64", help="grid h x w (working 384x512 -> 48x64)")
    parser.add_argument("--slices", default="0,96,32", help="linearise_edges values (0: every edge at once)")
    parser.add_argument("--iters", type=int, default=3)
    parser.add_argument("--allocators", default="glibc", help="glibc, tcmalloc or both (comma-separated)")
    parser.add_argument("--repeat", type=int, default=1, help="BAs run one after another in each process")
    parser.add_argument("--child", type=int, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    h, w = (int(v) for v in args.grid.split("x"))
    if args.child is not None:
        print(json.dumps(one(args.keyframes, args.radius, h, w, args.child, args.iters, args.repeat)))
        return
    rows = []
    for name in args.allocators.split(","):
        env = dict(os.environ)
        if name != "glibc":  # the library this process cannot load itself (it allocates already): its own child's
            env = allocator.preload_environment(name, env)
        for slices in (int(v) for v in args.slices.split(",")):
            argv = [sys.executable, __file__, "--keyframes", str(args.keyframes), "--radius", str(args.radius),
                    "--grid", args.grid, "--iters", str(args.iters), "--repeat", str(args.repeat),
                    "--child", str(slices)]
            rows.append(json.loads(subprocess.run(argv, check=True, capture_output=True, text=True,
                                                  env=env).stdout))
            if rows[-1]["allocator"] != name:
                raise SystemExit(f"the BA ran on {rows[-1]['allocator']}, not {name}: is its library installed?")
            print(f"{name}, slice {slices or 'all'}: {rows[-1]['peak_mb']:.0f} MB, {rows[-1]['seconds']:.1f} s",
                  file=sys.stderr)
    print("| allocator | keyframes | edges | edges per slice | peak RSS over start (MB) | RSS after (MB) | s: first BA "
          "/ later (median) | LM iterations | final cost |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        later = "–" if r["later_s"] is None else f"{r['later_s']:.2f}"
        print(f"| {r['allocator']} | {args.keyframes} | {r['edges']} | {r['slices'] or 'all'} | {r['peak_mb']:.0f} "
              f"| {r['after_mb']:.0f} | {r['seconds']:.2f} / {later} | {r['iterations']} | {r['cost']:.6g} |")


if __name__ == "__main__":
    main()
