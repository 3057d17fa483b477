"""``kmvipe eval ate``: absolute trajectory error of an estimate against ground truth."""
from __future__ import annotations

import argparse
import logging
import sys

from services.evaluation.ate import absolute_trajectory_error
from services.evaluation.trajectory_io import FORMATS, TrajectoryFormatError, read_trajectory

logger = logging.getLogger(__name__)


def register(subparsers) -> None:
    """Add ``eval`` (with sub-subcommand ``ate``) to a CLI's subparsers."""
    parser = subparsers.add_parser("eval", help="evaluate results against ground truth")
    sub = parser.add_subparsers(dest="eval_command", required=True)
    ate = sub.add_parser("ate", help="absolute trajectory error (position RMSE after alignment)")
    ate.add_argument("--gt", required=True, help="ground-truth trajectory file")
    ate.add_argument("--est", required=True, help="estimated trajectory file")
    ate.add_argument("--align", choices=("se3", "sim3", "none"), default="se3",
                     help="Umeyama alignment of the estimate onto the GT (sim3 for monocular)")
    ate.add_argument("--format", choices=FORMATS, default="tum", help="file format of both files")
    ate.add_argument("--max-diff", type=float, default=0.01,
                     help="max timestamp difference (s) for a pose pair (evo's --t_max_diff)")
    ate.set_defaults(func=run_ate)


def run_ate(args: argparse.Namespace) -> int:
    """Print RMSE, mean, median, max, pair count and scale; 0 on success, 2 on unreadable input."""
    try:
        gt = read_trajectory(args.gt, args.format)
        est = read_trajectory(args.est, args.format)
        res = absolute_trajectory_error(gt, est, align=args.align, max_diff=args.max_diff)
    except (OSError, TrajectoryFormatError, ValueError) as exc:
        logger.error("eval ate failed: %s", exc)
        sys.stderr.write(f"error: {exc}\n")
        return 2
    out = sys.stdout
    out.write(f"alignment  {args.align}\n")
    out.write(f"pairs      {res.n_pairs} (gt {len(gt.timestamps)}, est {len(est.timestamps)})\n")
    for name in ("rmse", "mean", "median", "max"):
        out.write(f"{name:<10} {getattr(res, name):.6f}\n")
    out.write(f"scale      {res.alignment.scale:.6f}\n")
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
