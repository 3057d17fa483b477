"""Benchmark: time per dense-BA iteration vs window size and edge count (synthetic windows, 1/8 grid).

Usage: ``python bench/ba.py [--device cpu|cuda] [--grid 48x64] [--windows 5,10,25] [--radii 2,3] [--iters 3]
[--codes none|ark|embed] [--dtype float32|float64] [--no-malloc-tuning]``
Prints a markdown table: keyframes, edges, residual pixels, seconds per LM iteration (linearise + Schur solve +
trial energy), and seconds per keyframe: one whole ``run_ba`` call of ``--frontend-iters`` iterations from a
window whose newest keyframe is off by 1 cm / 0.5 deg (what a frontend update does), ARK code sampling included.
"""
from __future__ import annotations

import argparse
import time
from dataclasses import replace

import torch

from services.ba.core import ba, synthetic
from services.ba.core.params import BAParams, RobustParams
from services.common.lifecycle import tune_malloc_for_tensors


def _timed(fn, device: torch.device) -> float:
    if device.type == "cuda":
        torch.cuda.synchronize()
    t0 = time.perf_counter()
    fn()
    if device.type == "cuda":
        torch.cuda.synchronize()
    return time.perf_counter() - t0


def _time_window(n: int, radius: int, h: int, w: int, args, device: torch.device) -> tuple[float, float]:
    win = synthetic.make_window(n=n, h=h, w=w, focal=0.55 * w, radius=radius, seed=0)
    gen = torch.Generator().manual_seed(1)
    perturbed = synthetic.perturb_poses(win.truth.poses, 0.01, 0.5, gen)
    start = ba.BAState(perturbed, win.truth.disparity * 1.1, win.truth.intrinsics)
    newest = win.truth.poses.clone()
    newest[-1] = perturbed[-1]
    update = ba.BAState(newest, win.truth.disparity, win.truth.intrinsics)
    problem = win.problem
    if args.codes != "none":
        # world-anchored codes: they agree across views, as on a static scene
        problem = problem._replace(codes=synthetic.world_codes(win.truth, 32, freq=0.5, seed=2).float())
    move = lambda t: None if t is None else t.to(device)  # noqa: E731
    start, update = (ba.BAState(*(move(t) for t in s)) for s in (start, update))
    problem = ba.BAProblem(*(move(t) for t in problem))
    robust = RobustParams(use_ark=args.codes != "none", alpha_static=0.0, scale=0.2)
    params = BAParams(iterations=args.iters, optimise_focal=True, rel_tol=0.0, lm_max=1e30,
                      lambda_embed=1.0 if args.codes == "embed" else 0.0, robust=robust, compute_dtype=args.dtype)
    ba.run_ba(start, problem, replace(params, iterations=1))  # warm-up (allocations, kernels)
    per_iter = _timed(lambda: ba.run_ba(start, problem, params), device) / args.iters
    frontend = replace(params, iterations=args.frontend_iters, rel_tol=BAParams.rel_tol, lm_max=BAParams.lm_max)
    per_kf = _timed(lambda: ba.run_ba(update, problem, frontend), device)
    return per_iter, per_kf


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--grid", default="48x64", help="grid h x w (working 384x512 -> 48x64)")
    parser.add_argument("--windows", default="5,10,25")
    parser.add_argument("--radii", default="2,3")
    parser.add_argument("--iters", type=int, default=3)
    parser.add_argument("--frontend-iters", type=int, default=3, help="iterations per keyframe update")
    parser.add_argument("--codes", choices=("none", "ark", "embed"), default="ark",
                        help="32-d codes: none (fixed kernel), ark (the service default), embed (ARK + embedding term)")
    parser.add_argument("--dtype", choices=("float32", "float64"), default="float32", help="per-pixel arithmetic")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (the ba service uses 1)")
    parser.add_argument("--no-malloc-tuning", action="store_true", help="leave glibc malloc at its defaults")
    parser.add_argument("--keep-mib", type=int, default=None, help="freed heap glibc keeps (tune_malloc_for_tensors)")
    args = parser.parse_args()
    if not args.no_malloc_tuning:
        tune_malloc_for_tensors() if args.keep_mib is None else tune_malloc_for_tensors(args.keep_mib)
    if args.threads:
        torch.set_num_threads(args.threads)
    h, w = (int(v) for v in args.grid.split("x"))
    device = torch.device(args.device)
    print(f"device {device}, threads {torch.get_num_threads()}, grid {h}x{w}, codes {args.codes}, {args.dtype}, "
          f"malloc tuning {not args.no_malloc_tuning}")
    print(f"| keyframes | radius | edges | residual px | s / iteration | s / keyframe ({args.frontend_iters} it.) |")
    print("|---|---|---|---|---|---|")
    for n in (int(v) for v in args.windows.split(",")):
        for radius in (int(v) for v in args.radii.split(",")):
            edges = len(synthetic.temporal_edges(n, radius)[0])
            per_iter, per_kf = _time_window(n, radius, h, w, args, device)
            print(f"| {n} | {radius} | {edges} | {edges * h * w} | {per_iter:.3f} | {per_kf:.3f} |", flush=True)


if __name__ == "__main__":
    main()
