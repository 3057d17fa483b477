"""Render time of the synthetic world; optionally writes a montage (rgb | depth | labels) of a few frames.

    .venv/bin/python bench/synth.py --frames 200
    .venv/bin/python bench/synth.py --frames 200 --montage /tmp/synth_montage.png
"""

from __future__ import annotations

import argparse
import time

import cv2
import numpy as np

from services.synth import SynthConfig, SynthWorld

DEPTH_VIS_MAX_M = 8.0  # depth colour map saturates here
MONTAGE_FRAMES = 5


def montage(world: SynthWorld, path: str) -> None:
    """Rows of rgb | depth (viridis) | labels (dynamic pixels brightened) for a few frames, written as PNG."""
    palette = np.random.default_rng(3).integers(0, 255, (len(world.label_names), 3)).astype(np.uint8)
    rows = []
    for i in np.linspace(0, len(world) - 1, MONTAGE_FRAMES).astype(int):
        f = world.render(int(i))
        depth8 = (np.clip(f.depth / DEPTH_VIS_MAX_M, 0, 1) * 255).astype(np.uint8)
        depth_rgb = cv2.applyColorMap(depth8, cv2.COLORMAP_VIRIDIS)[..., ::-1]
        labels = palette[f.labels]
        labels[f.dynamic] = labels[f.dynamic] // 2 + 127
        rows.append(np.concatenate([f.rgb, depth_rgb, labels], axis=1))
    image = np.concatenate(rows, axis=0)
    cv2.imwrite(path, cv2.cvtColor(image, cv2.COLOR_RGB2BGR))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=200, help="frames to render")
    parser.add_argument("--width", type=int, default=512)
    parser.add_argument("--height", type=int, default=384)
    parser.add_argument("--threads", type=int, default=0, help="cv2 threads (0: leave as is)")
    parser.add_argument("--montage", default="", help="write a PNG montage here")
    args = parser.parse_args()
    if args.threads:
        cv2.setNumThreads(args.threads)
    start = time.perf_counter()
    world = SynthWorld(SynthConfig(width=args.width, height=args.height, n_frames=args.frames))
    built = time.perf_counter() - start
    start, cpu_start = time.perf_counter(), time.process_time()
    for i in range(len(world)):
        world.render(i)
    total, cpu = time.perf_counter() - start, time.process_time() - cpu_start
    print(f"synth {args.width}x{args.height}: build {built:.2f} s, render {args.frames} frames {total:.2f} s wall "
          f"({1000 * total / args.frames:.1f} ms/frame, {args.frames / total:.1f} fps), "
          f"{cpu:.2f} s CPU (all threads; wall is inflated when other jobs share the cores)")
    if args.montage:
        montage(world, args.montage)
        print(f"montage written to {args.montage}")


if __name__ == "__main__":
    main()
