"""OpenCV DIS settings of BA's flow targets against exact flow: accuracy of the grid targets and time per flow.

Pairs of frames of the synthetic hand-held profiles (services/synth/profiles.py) rendered at the working size,
a few frames apart as keyframes are; the true flow of every pixel comes from the rendered depth and the two
poses (``services.synth.geometry.static_correspondence``), occluded pixels left out. For each DIS setting:
the median end-point error of the dense flow, the mean error of the 1/8-grid targets BA uses (the block mean of
the flow, over cells seen whole in both frames), the median ratio of estimated to true flow magnitude (a
bias that would scale BA's rotations), and the time per flow on one thread.

Usage: ``python bench/flow_settings.py [--size 512x384] [--markdown]``
"""
from __future__ import annotations

import argparse
import time
from typing import NamedTuple

import cv2
import numpy as np
from tqdm import tqdm

from services.synth.geometry import static_correspondence, visible_in_j
from services.synth.profiles import profile, profile_world

PRESETS = {"ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST, "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
           "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM}
# (profile, frame gaps): turns, pans, a backward walk, a wide lens and a faint wall, at keyframe-like spacings
PAIRS = (("rot1", (3, 6)), ("fast_pan", (2, 4)), ("rot3", (2,)), ("backwards", (6, 10)), ("fov80", (4,)),
         ("low_texture", (4,)))
STARTS = (10, 35)
# name -> (preset, finest scale, patch stride or None for the preset's, gradient descent iterations or None)
SETTINGS = {
    "medium, level 0, stride 3 (the default)": ("medium", 0, None, None),
    "medium, level 0, stride 4": ("medium", 0, 4, None),
    "medium, level 0, stride 4, 12 iterations": ("medium", 0, 4, 12),
    "medium, level 0, stride 6": ("medium", 0, 6, None),
    "medium, level 1 (the preset's own)": ("medium", 1, None, None),
    "fast, level 0": ("fast", 0, None, None),
    "ultrafast, level 0": ("ultrafast", 0, None, None),
}


class Pair(NamedTuple):
    image_a: np.ndarray  # (H, W) uint8 grey
    image_b: np.ndarray
    flow: np.ndarray  # (H, W, 2) float32 true flow a -> b
    seen: np.ndarray  # (H, W) bool: in view in b and not occluded there


class Score(NamedTuple):
    epe_px: float  # median end-point error of the dense flow
    cell_px: float  # mean error of the grid targets
    magnitude_ratio: float  # median |estimated| / |true| where the true flow exceeds 2 px
    ms: float  # per flow, one thread


def render_pairs(width: int, height: int) -> list[Pair]:
    pairs = []
    for name, gaps in tqdm(PAIRS, desc="render", unit="profile"):
        world = profile_world(profile(name, 60), width, height, 30.0)
        for start in STARTS:
            for gap in gaps:
                a, b = world.render(start), world.render(start + gap)
                corr = static_correspondence(a.depth, a.intrinsics, a.world_from_cam, b.world_from_cam)
                grey = [cv2.cvtColor(f.rgb, cv2.COLOR_RGB2GRAY) for f in (a, b)]
                pairs.append(Pair(*grey, corr.flow.astype(np.float32), visible_in_j(corr, b.depth) & corr.in_view))
    return pairs


def block_mean(x: np.ndarray, grid: int = 8) -> np.ndarray:
    h, w = x.shape[0] // grid, x.shape[1] // grid
    return x[: h * grid, : w * grid].reshape(h, grid, w, grid, *x.shape[2:]).mean(axis=(1, 3))


def score(pairs: list[Pair], preset: str, finest: int, stride: int | None, iterations: int | None) -> Score:
    epe, cells, ratio, seconds = [], [], [], 0.0
    for p in pairs:
        dis = cv2.DISOpticalFlow_create(PRESETS[preset])
        dis.setFinestScale(finest)
        if stride is not None:
            dis.setPatchStride(stride)
        if iterations is not None:
            dis.setGradientDescentIterations(iterations)
        began = time.perf_counter()
        flow = dis.calc(p.image_a, p.image_b, None)
        seconds += time.perf_counter() - began
        epe.append(np.median(np.linalg.norm(flow - p.flow, axis=-1)[p.seen]))
        whole = block_mean(p.seen.astype(np.float32)) > 0.99
        cells.append(np.linalg.norm(block_mean(flow) - block_mean(p.flow), axis=-1)[whole].mean())
        true = np.linalg.norm(p.flow, axis=-1)
        moving = p.seen & (true > 2)
        ratio.append(np.median(np.linalg.norm(flow, axis=-1)[moving] / true[moving]))
    return Score(float(np.mean(epe)), float(np.mean(cells)), float(np.median(ratio)), 1000 * seconds / len(pairs))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", default="512x384", help="width x height of the rendered pairs (the working size)")
    parser.add_argument("--markdown", action="store_true", help="print the table as markdown")
    args = parser.parse_args()
    width, height = (int(v) for v in args.size.split("x"))
    cv2.setNumThreads(1)  # ba computes its flows on one thread
    pairs = render_pairs(width, height)
    rows = [(name, score(pairs, *setting)) for name, setting in tqdm(SETTINGS.items(), desc="DIS", unit="setting")]
    head = ("setting", "median EPE px", "grid target error px", "|flow| ratio", "ms per flow")
    body = [(name, f"{s.epe_px:.3f}", f"{s.cell_px:.3f}", f"{s.magnitude_ratio:.4f}", f"{s.ms:.1f}") for name, s in rows]
    if args.markdown:
        print("\n".join("| " + " | ".join(r) + " |" for r in [head, ("---",) * len(head), *body]))
    else:
        width_0 = max(len(r[0]) for r in body)
        print("\n".join(f"{r[0]:<{width_0}}  " + "  ".join(f"{c:>13}" for c in r[1:]) for r in [head, *body]))
    base, now = rows[0][1], rows[1][1]
    print(f"\nsummary: {len(pairs)} pairs at {width}x{height}; stride 4 takes {now.ms / base.ms:.0%} of the default's "
          f"time with grid targets {now.cell_px:.3f} px off against {base.cell_px:.3f} (synthetic walls are textured: "
          f"see docs/BENCHMARKS.md for TartanAir)")


if __name__ == "__main__":
    main()
