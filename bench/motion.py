"""Motion-only alignment's cost (services/ba/frontend/motion.py), the solve tracking runs on every frame.

A camera 30 cm and ~1.3 deg from one keyframe with a KITTI-sized grid (30 x 98 cells at half working size), flow
targets from the exact pose plus 0.05 px noise; the solve starts at the keyframe. Prints ms per ``align`` call,
its steps and the pose error.

Usage:
  python bench/motion.py [--calls 50] [--height 30 --width 98]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from services.ba.core import projective, se3  # noqa: E402
from services.ba.frontend import motion  # noqa: E402
from services.ba.frontend.params import MotionParams  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--calls", type=int, default=50)
    parser.add_argument("--height", type=int, default=30, help="grid cells")
    parser.add_argument("--width", type=int, default=98, help="grid cells")
    args = parser.parse_args()
    torch.set_num_threads(1)
    gen = torch.Generator().manual_seed(0)
    h, w = args.height, args.width
    keyframe = torch.eye(4, dtype=torch.float64)[None]
    disparity = torch.rand(1, h, w, dtype=torch.float64, generator=gen) * 0.5 + 0.1
    intrinsics = torch.tensor([90.0, 90.0, w / 2, h / 2], dtype=torch.float64)
    truth = se3.exp(torch.tensor([0.02, -0.01, 0.3, 0.01, 0.02, -0.01], dtype=torch.float64))
    pixels = projective.pixel_grid(h, w, torch.float64, "cpu")
    coords = projective.reproject(keyframe, truth[None], disparity.reshape(1, -1), pixels, intrinsics, False).coords
    targets = (coords + 0.05 * torch.randn(coords.shape, dtype=torch.float64, generator=gen)).reshape(1, h, w, 2)
    confidence = torch.ones(1, h, w, dtype=torch.float64)
    start = np.eye(4)
    # numpy arrays, as the tracking process holds them
    problem = [t.numpy() for t in (keyframe, disparity, targets, confidence, intrinsics)]
    result = motion.align(start, *problem, MotionParams())
    began = time.perf_counter()
    for _ in range(args.calls):
        motion.align(start, *problem, MotionParams())
    ms = (time.perf_counter() - began) / args.calls * 1e3
    error = float(np.abs(result.pose - truth.numpy()).max())
    print(f"motion-only alignment, {h}x{w} grid: {ms:.1f} ms per call, {result.steps} steps, "
          f"pose error {error:.1e} (max abs of the 4x4 difference)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
