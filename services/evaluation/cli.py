"""``kmvipe eval ate``: absolute trajectory error of an estimate against ground truth, with the relative pose error
(translation and rotation, evo's definitions) of the same association and alignment beside it."""
from __future__ import annotations

import argparse
import logging
import sys

from services.evaluation.ate import ALIGNMENTS, absolute_trajectory_error
from services.evaluation.rpe import DELTA_UNITS, trajectory_rpe
from services.evaluation.trajectory_io import FORMATS, TrajectoryFormatError, read_trajectory

logger = logging.getLogger(__name__)

STATISTICS = ("rmse", "mean", "median", "std", "min", "max")


def register(subparsers) -> None:
    """Add ``eval`` (with sub-subcommand ``ate``, also called ``rpe``) to a CLI's subparsers."""
    parser = subparsers.add_parser("eval", help="evaluate results against ground truth")
    sub = parser.add_subparsers(dest="eval_command", required=True)
    ate = sub.add_parser("ate", aliases=["rpe"],
                         help="absolute trajectory error (position RMSE after alignment) and relative pose error")
    ate.add_argument("--gt", required=True, help="ground-truth trajectory file")
    ate.add_argument("--est", required=True, help="estimated trajectory file")
    ate.add_argument("--align", choices=ALIGNMENTS, default="se3",
                     help="Umeyama alignment of the estimate onto the GT (sim3 for monocular)")
    ate.add_argument("--format", choices=FORMATS, default="tum", help="file format of both files")
    ate.add_argument("--max-diff", type=float, default=0.01,
                     help="max timestamp difference (s) for a pose pair (evo's --t_max_diff)")
    ate.add_argument("--delta", type=float, default=1,
                     help="RPE: distance between the poses of a pair, in --delta-unit (evo's --delta)")
    ate.add_argument("--delta-unit", choices=DELTA_UNITS, default="frames",
                     help="RPE: frames (matched poses) or m (path length travelled) (evo's --delta_unit f|m)")
    ate.add_argument("--all-pairs", action="store_true",
                     help="RPE: every pose starts a pair, not only the ends of the previous one (evo's --all_pairs)")
    ate.set_defaults(func=run_ate)


def run_ate(args: argparse.Namespace) -> int:
    """Print ATE and RPE statistics, pair counts and scale; 0 on success, 2 on unreadable or unusable input."""
    try:
        gt = read_trajectory(args.gt, args.format)
        est = read_trajectory(args.est, args.format)
        res = absolute_trajectory_error(gt, est, align=args.align, max_diff=args.max_diff)
        rel = trajectory_rpe(gt, est, align=args.align, max_diff=args.max_diff, delta=args.delta,
                             delta_unit=args.delta_unit, all_pairs=args.all_pairs).rpe
    except (OSError, TrajectoryFormatError, ValueError) as exc:
        logger.error("eval ate failed: %s", exc)
        sys.stderr.write(f"error: {exc}\n")
        return 2
    out = sys.stdout
    delta = f"{rel.delta:g} {rel.delta_unit}, {'all' if rel.all_pairs else 'consecutive'} pairs"
    out.write(f"alignment  {args.align}\n")
    out.write(f"pairs      {res.n_pairs} (gt {len(gt.timestamps)}, est {len(est.timestamps)})\n")
    out.write(f"scale      {res.alignment.scale:.6f}\n")
    out.write(f"rpe pairs  {rel.translation.n} (delta {delta})\n")
    out.write(f"{'':<10} {'ATE (m)':<12} {'RPE t (m)':<12} {'RPE R (deg)'}\n")
    for name in STATISTICS:
        values = (getattr(res, name), getattr(rel.translation, name), getattr(rel.rotation, name))
        out.write(f"{name:<10} " + " ".join(f"{v:<12.6f}" for v in values).rstrip() + "\n")
    return 0


def main(argv: list[str] | None = None) -> int:
    """Stand-alone entry point: ``python -m services.evaluation.cli ate --gt ... --est ...``."""
    parser = argparse.ArgumentParser(prog="kmvipe-eval")
    sub = parser.add_subparsers(dest="command", required=True)
    register(sub)
    args = parser.parse_args(["eval", *(argv if argv is not None else sys.argv[1:])])
    return args.func(args)


if __name__ == "__main__":
    raise SystemExit(main())
