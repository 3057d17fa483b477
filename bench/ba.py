"""Benchmark: time per dense-BA iteration vs window size and edge count (synthetic windows, 1/8 grid).

Usage: ``python bench/ba.py [--device cpu|cuda] [--grid 48x64] [--windows 5,10,25] [--radii 2,3] [--iters 3]``
Prints a markdown table: keyframes, edges, residual pixels, seconds per LM iteration (linearise + Schur solve +
trial energy), seconds per keyframe for a frontend update of ``--frontend-iters`` iterations.
"""
from __future__ import annotations

import argparse
import time

import torch

from services.ba.core import ba, synthetic
from services.ba.core.params import BAParams, RobustParams


def _time_window(n: int, radius: int, h: int, w: int, iters: int, device: torch.device, embed: bool) -> float:
    win = synthetic.make_window(n=n, h=h, w=w, focal=0.55 * w, radius=radius, seed=0)
    gen = torch.Generator().manual_seed(1)
    start = ba.BAState(synthetic.perturb_poses(win.truth.poses, 0.01, 0.5, gen),
                       win.truth.disparity * 1.1, win.truth.intrinsics)
    problem = win.problem
    if embed:
        codes = torch.randn(n, h, w, 32, generator=gen, dtype=torch.float32)
        problem = problem._replace(codes=codes)
    move = lambda t: None if t is None else t.to(device)  # noqa: E731
    start = ba.BAState(*(move(t) for t in start))
    problem = ba.BAProblem(*(move(t) for t in problem))
    params = BAParams(iterations=iters, optimise_focal=True, rel_tol=0.0, lm_max=1e30,
                      lambda_embed=1.0 if embed else 0.0, robust=RobustParams(use_ark=embed))
    ba.run_ba(start, problem, BAParams(iterations=1))  # warm-up (allocations, kernels)
    if device.type == "cuda":
        torch.cuda.synchronize()
    t0 = time.perf_counter()
    ba.run_ba(start, problem, params)
    if device.type == "cuda":
        torch.cuda.synchronize()
    return (time.perf_counter() - t0) / iters


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--grid", default="48x64", help="grid h x w (working 384x512 -> 48x64)")
    parser.add_argument("--windows", default="5,10,25")
    parser.add_argument("--radii", default="2,3")
    parser.add_argument("--iters", type=int, default=3)
    parser.add_argument("--frontend-iters", type=int, default=4, help="iterations per keyframe update")
    parser.add_argument("--embed", action="store_true", help="ARK + embedding term with 32-d codes")
    parser.add_argument("--threads", type=int, default=0, help="torch threads (0 = default)")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    h, w = (int(v) for v in args.grid.split("x"))
    device = torch.device(args.device)
    print(f"device {device}, threads {torch.get_num_threads()}, grid {h}x{w}, embed {args.embed}")
    print("| keyframes | radius | edges | residual px | s / iteration | s / keyframe |")
    print("|---|---|---|---|---|---|")
    for n in (int(v) for v in args.windows.split(",")):
        for radius in (int(v) for v in args.radii.split(",")):
            edges = len(synthetic.temporal_edges(n, radius)[0])
            sec = _time_window(n, radius, h, w, args.iters, device, args.embed)
            print(f"| {n} | {radius} | {edges} | {edges * h * w} | {sec:.3f} | {sec * args.frontend_iters:.3f} |",
                  flush=True)


if __name__ == "__main__":
    main()
