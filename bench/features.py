"""Time split of the features service per keyframe and per non-keyframe, onnxruntime vs torch.

    .venv/bin/python bench/features.py --threads 2 --repeats 3

Prints a markdown table (median seconds) and the command. Uses KITTI 07 frames when ../shared/data is
present (else a synthetic frame); depth is timed only when a depth model is installed.
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("KMVIPE_DATA_DIR", ROOT.parent / "shared" / "data"))


def _frames(n: int) -> list[np.ndarray]:
    import cv2

    rgb = DATA / "kitti07_160" / "rgb"
    if rgb.is_dir():
        return [cv2.imread(str(rgb / f"{i:06d}.png"), cv2.IMREAD_GRAYSCALE) for i in range(n)]
    from services.synth import SynthConfig, SynthWorld

    world = SynthWorld(SynthConfig(n_frames=n))
    return [world.render(i).rgb for i in range(n)]


def _median(xs: list[float]) -> float:
    return statistics.median(xs) if xs else float("nan")


def bench(args: argparse.Namespace) -> list[tuple[str, str, float]]:
    from services.common.models import ModelStore
    from services.common.models.backbones import normalise_rgb
    from services.common.models.loaders import load_backbone, load_depth_model
    from services.features.core.geometry import resize_to_working, to_grey, to_rgb, working_size
    from services.features.core.keyframes import KeyframeSelector
    from services.features.core.pca import fit_pca, project
    from services.features.core.pyramid import PyramidParams, backbone_map

    torch.set_num_threads(args.threads)
    store = ModelStore(Path(args.models_dir) if args.models_dir else None)
    frames = _frames(args.repeats + 1)
    size = working_size(*frames[0].shape[:2])
    rows: list[tuple[str, str, float]] = []

    # non-keyframe path: resize + grey + DIS flow against a reference
    sel = KeyframeSelector()
    sel.set_reference(to_grey(resize_to_working(to_rgb(frames[0]), size)))
    t_resize, t_flow = [], []
    for img in frames[1:] * 5:
        t0 = time.perf_counter()
        grey = to_grey(resize_to_working(to_rgb(img), size))
        t1 = time.perf_counter()
        sel.motion(grey)
        t_resize.append(t1 - t0)
        t_flow.append(time.perf_counter() - t1)
    rows += [("all", "resize", _median(t_resize)), ("all", "flow", _median(t_flow)),
             ("all", "non-keyframe total", _median(t_resize) + _median(t_flow))]  # fmt: skip

    x = normalise_rgb(resize_to_working(to_rgb(frames[0]), size))
    scales = PyramidParams().scales
    feats = None
    for runtime in args.runtimes:
        bb = load_backbone(args.backbone, store, args.device, runtime=runtime, threads=args.threads)
        backbone_map(x, bb, 1.0, 14)  # warm-up
        total = 0.0
        for s in scales:
            ts = []
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                fmap = backbone_map(x, bb, s, 14)
                ts.append(time.perf_counter() - t0)
            rows.append((runtime, f"scale {s:g} ({fmap.shape[2]}×{fmap.shape[3]} patches)", _median(ts)))
            total += _median(ts)
        rows.append((runtime, "pyramid total", total))
        feats = np.random.default_rng(0).standard_normal((384, size.height // 8, size.width // 8), np.float32)
        feats /= np.linalg.norm(feats, axis=0, keepdims=True)
    basis = fit_pca(feats.reshape(384, -1).T, 32, "bench")
    t = [time.perf_counter()]
    for _ in range(10):
        project(basis, feats)
    rows.append(("all", "pca project", (time.perf_counter() - t[0]) / 10))
    if args.depth_model:
        dm = load_depth_model(args.depth_model, store, args.device)
        from services.features.core.depth import model_disparity

        t0 = time.perf_counter()
        model_disparity(x, dm, dm.patch_size)
        rows.append(("torch", "depth", time.perf_counter() - t0))
    else:
        rows.append(("-", "depth", float("nan")))
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--device", default="cpu")
    p.add_argument("--backbone", default="dinov2-vits14-imgfocus")
    p.add_argument("--runtimes", nargs="+", default=["onnx", "torch"])
    p.add_argument("--depth-model", default="")
    p.add_argument("--models-dir", default=os.environ.get("KMVIPE_MODELS_DIR", ""))
    args = p.parse_args(argv)
    rows = bench(args)
    print(f"command: {' '.join([Path(sys.executable).name, *sys.argv])}")
    print(f"device: {args.device}, threads: {args.threads}, torch {torch.__version__}\n")
    print("| runtime | stage | median ms |\n|---|---|---|")
    for runtime, stage, sec in rows:
        print(f"| {runtime} | {stage} | {sec * 1000:.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
