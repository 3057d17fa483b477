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
  <profile>   a bench/robustness.py motion profile (e.g. rot1, turn180) streamed through bench/frontend.py's
              run_frontend with oracle label codes (noise ``--noise``) at the working grid's cell centres; ATE
              as % of the path. The in-process frontend takes no codes by itself: this bench swaps in a
              Frontend that attaches them to every keyframe and uses the variant's kernel (window and global BA).

ba.py's _frozen still calls robust.ark_alpha (the centred map) directly; until it calls robust.ark_shape, the
paper rows run with robust.ark_alpha replaced by the paper map in this process (``_paper_hook``).

Usage: ``python bench/ablation_kernel.py [--scenes dynamic,rot1,turn180] [--starts 3] [--frames 120]``
"""
from __future__ import annotations

import argparse
import contextlib
import dataclasses
import inspect
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import ba_dynamic  # noqa: E402
import frontend as frontend_bench  # noqa: E402
import robustness  # noqa: E402

from services.ba.core import ba, robust, synthetic  # noqa: E402
from services.ba.core.params import BAParams, RobustParams  # noqa: E402
from services.ba.frontend.frontend import Frontend, KeyframeInput  # noqa: E402
from services.ba.settings import BaSettings  # noqa: E402
from services.common.config import LogSettings  # noqa: E402
from services.common.logs import setup_logging  # noqa: E402
from services.evaluation.trajectory_io import Trajectory  # noqa: E402
from services.synth.config import SynthConfig  # noqa: E402
from services.synth.oracle import label_vectors, oracle_features  # noqa: E402
from services.synth.render import SynthWorld  # noqa: E402


KERNELS = {"ARK centred": {"use_ark": True, "ark_mode": "centred"}, "ARK paper": {"use_ark": True, "ark_mode": "paper"},
           "Cauchy": {"use_ark": False, "fixed_alpha": 0.0}, "L2": {"use_ark": False, "fixed_alpha": 2.0}}


def kernels(base: RobustParams) -> dict[str, RobustParams]:
    """The four kernels on ``base`` (its scale and refresh kept: the frontend's c is 0.2, ba_dynamic's 0.5)."""
    return {name: dataclasses.replace(base, **fields) for name, fields in KERNELS.items()}


@contextlib.contextmanager
def _paper_hook(rob: RobustParams):
    """Route ba.py's shape map through robust.ark_shape for ``rob`` (a no-op once ba.py does so itself)."""
    if rob.ark_mode == "centred" or "ark_shape" in inspect.getsource(ba):
        yield
        return
    original = robust.ark_alpha
    robust.ark_alpha = lambda cosine, *_args: robust.ark_shape(cosine, rob)
    try:
        yield
    finally:
        robust.ark_alpha = original


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
            with _paper_hook(rob):
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
    rows = []
    for kname, rob in kernels(BaSettings().ba_params().robust).items():
        for lam in (0.0, args.lambda_embed):
            original = frontend_bench.Frontend
            frontend_bench.Frontend = _coded_frontend(rob, lam, codes_of)
            t0 = time.perf_counter()
            try:
                with _paper_hook(rob):
                    run = frontend_bench.run_frontend(frames, progress=False)
            finally:
                frontend_bench.Frontend = original
            row = robustness.score(name, Trajectory(stamps, poses), run.trajectory(), args.frames,
                                   float(world.intrinsics[0]), run)
            rows.append((name, kname, lam, f"{row.ate_pct_path:.2f} % path", f"{row.max_rot_err_deg:.2f}",
                         f"posed {row.posed_pct:.0f} %, focal err {row.focal_err_pct:.1f} %, "
                         f"{time.perf_counter() - t0:.0f} s"))
            print(rows[-1], flush=True)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", default="dynamic,rot1", help="dynamic and/or bench/robustness.py profiles")
    parser.add_argument("--starts", type=int, default=3, help="perturbed starts of the dynamic window")
    parser.add_argument("--frames", type=int, default=120, help="frames of a motion profile")
    parser.add_argument("--width", type=int, default=512)
    parser.add_argument("--height", type=int, default=384)
    parser.add_argument("--noise", type=float, default=0.3, help="oracle code noise ratio (profiles)")
    parser.add_argument("--lambda-embed", type=float, default=1.0, help="embedding residual weight when on")
    args = parser.parse_args()
    torch.set_num_threads(1)
    setup_logging("bench-ablation-kernel", LogSettings(level="ERROR"))
    rows = []
    for scene in (s for s in args.scenes.split(",") if s):
        rows += run_dynamic(args) if scene == "dynamic" else run_profile(scene, args)
    print("| scene | kernel | lambda_embed | ATE | max rot err (deg) | IoU / notes |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print("| " + " | ".join(str(c) for c in r) + " |")


if __name__ == "__main__":
    main()
