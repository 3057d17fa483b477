"""A fixed CPU workload timed on one thread: how fast this machine is right now, printed beside a benchmark.

The reference machine's speed drifts: the same code's CPU seconds on lossless KITTI 07 differed by ~30 % within one
session and ~1.7x between sessions (docs/BENCHMARKS.md, forty-eighth and fifty-first sessions). Figures of different
runs compare only at the same speed, so `bench/live.py` measures this before each run and prints it in its table.
The workload is the two kinds of work ba's CPU goes to: DIS optical flow (OpenCV, the medium preset) on a fixed
textured pair at KITTI 07's working size, and float64 matrix products (BA's normal equations). Each is the median
of a few repeats, in a process of its own with every thread pool at one thread.

Usage:
  python bench/machine_reference.py            # prints the two times
  python bench/machine_reference.py --json     # the same as JSON (what bench/live.py reads)
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ONE_THREAD = {name: "1" for name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}
FLOW_SHAPE = (240, 808)  # KITTI 07's working size
MATMUL_SIDE = 384


def measure(repeats: int = 7) -> dict[str, float]:
    """Median milliseconds of one DIS flow and of one float64 matrix product in this process."""
    import cv2
    import numpy as np

    cv2.setNumThreads(1)
    rng = np.random.default_rng(0)
    first = cv2.GaussianBlur((rng.random(FLOW_SHAPE) * 255).astype(np.uint8), (0, 0), 2.0)
    second = np.roll(first, (2, 3), axis=(0, 1))
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    a = rng.standard_normal((MATMUL_SIDE, MATMUL_SIDE))

    def median_ms(work) -> float:
        work()  # warm: first-call allocations and lazy initialisation are not the machine's speed
        times = []
        for _ in range(repeats):
            began = time.perf_counter()
            work()
            times.append(1000 * (time.perf_counter() - began))
        return float(np.median(times))

    return {"dis_flow_ms": round(median_ms(lambda: dis.calc(first, second, None)), 2),
            "matmul_ms": round(median_ms(lambda: a @ a), 2)}


def reference(timeout_s: float = 120.0) -> dict[str, float] | None:
    """`measure` in a fresh one-thread process (thread pools are fixed when numpy loads); None if it failed."""
    try:
        done = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--json"], capture_output=True,
                              text=True, timeout=timeout_s, env={**os.environ, **ONE_THREAD})
        return json.loads(done.stdout) if done.returncode == 0 else None
    except (subprocess.TimeoutExpired, json.JSONDecodeError):
        return None


def describe(ref: dict[str, float] | None) -> str:
    """One table cell."""
    if not ref:
        return "– (not measured)"
    h, w = FLOW_SHAPE
    return (f"DIS flow {w}×{h} {ref['dis_flow_ms']:.1f} ms, float64 matmul {MATMUL_SIDE}² {ref['matmul_ms']:.2f} ms "
            "(one thread, median)")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    parser.add_argument("--json", action="store_true", help="print JSON")
    args = parser.parse_args()
    if args.json:
        print(json.dumps(measure()))
        return 0
    ref = reference()
    print(describe(ref))
    return 0 if ref else 1


if __name__ == "__main__":
    sys.exit(main())
