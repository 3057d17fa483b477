"""The focal the flow alone supports (issue 13): BA over short windows of frames whose poses are held at the ground
truth, with only the depths and the focal free (and, with ``--principal-point``, the principal point).

A calibration-free run estimates poses, depths and intrinsics together, so its focal error mixes what the flow
says with how the joint problem settles. Held at exact (or surveyed) poses, the same BA, flow targets and kernel
as the pipeline's focal BAs leave only the flow's evidence: a window's focal error here is what its DIS flow
supports, and the spread over windows is how much one window can be trusted. Each window is ``--keyframes``
frames ``--gap`` apart, one every ``--every`` frames, with edges up to two keyframes apart both ways (as the
pipeline's temporal edges), the focal starting at the true one.

Where the flow agrees with the truth the windows cluster at 0 %; a sequence whose windows cluster elsewhere
carries the bias in its flow (or in its ground truth), and no BA schedule on top of that flow can remove it.

Usage:
  python bench/focal_evidence.py                                     # kitti, tartanair, desk
  python bench/focal_evidence.py --profiles rot1,fov110 --markdown   # synthetic profiles (rendered once, cached)
  python bench/focal_evidence.py --profiles kitti --gap 1 --principal-point
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
from robustness import REAL, add_sequence_arguments, cached_profile, profile_names  # noqa: E402

from services.ba.core import flow as core_flow  # noqa: E402
from services.ba.core.ba import BAProblem, BAState, run_ba  # noqa: E402
from services.ba.core.params import BAParams, FlowParams  # noqa: E402
from services.ba.frontend.params import focal_ba  # noqa: E402
from services.ba.settings import BaSettings  # noqa: E402
from services.common.config import LogSettings  # noqa: E402
from services.common.logs import setup_logging  # noqa: E402
from services.features.core.geometry import Intrinsics, resize_to_working, working_size  # noqa: E402
from services.ingest.sources import SourceFrame, open_source  # noqa: E402
from services.runner.groundtruth import source_groundtruth, source_intrinsics  # noqa: E402

EDGE_REACH = 2  # keyframes apart an edge joins, both ways
START_DISPARITY = 0.2  # 1/m everywhere: BA finds the depths (the poses, and so the scale, are the truth's)
DIVERGED_PCT = 20.0  # a window further than this from the truth found no focal (a bare view): counted apart


def window_focal(images: list[np.ndarray], world_from_cam: np.ndarray, grid: Intrinsics, params: BAParams,
                 flow_params: FlowParams) -> torch.Tensor:
    """Grid intrinsics (4,) BA settles on over ``images`` (working size) held at ``world_from_cam`` (N, 4, 4)."""
    n = len(images)
    edges = [(i, j) for i in range(n) for j in range(n) if i != j and abs(i - j) <= EDGE_REACH]
    targets, confidence = core_flow.edge_targets(images, edges, flow_params)
    h, w = targets.shape[1:3]
    problem = BAProblem(torch.tensor([e[0] for e in edges]), torch.tensor([e[1] for e in edges]),
                        torch.from_numpy(targets), torch.from_numpy(confidence))
    state = BAState(torch.from_numpy(world_from_cam).to(torch.float64),
                    torch.full((n, h, w), START_DISPARITY, dtype=torch.float64),
                    torch.tensor(grid.as_array(), dtype=torch.float64))
    return run_ba(state, problem, dataclasses.replace(params, fixed_poses=n)).state.intrinsics


def sequence_errors(source: str, keyframes: int, gap: int, every: int, params: BAParams, flow_params: FlowParams,
                    name: str) -> np.ndarray:
    """Focal error (%) of every window of ``source`` (an image folder with ground truth and intrinsics)."""
    truth, gt = source_intrinsics(source), source_groundtruth(source)
    if truth is None or gt is None:
        raise SystemExit(f"{source}: needs groundtruth.txt and camera.txt (or KITTI's calib.txt) beside the images")
    frames = [f for f in open_source(source).frames() if isinstance(f, SourceFrame)]
    if len(frames) != len(gt.world_from_cam):
        raise SystemExit(f"{source}: {len(frames)} frames but {len(gt.world_from_cam)} ground-truth poses")
    height, width = frames[0].rgb.shape[:2]
    size = working_size(height, width)
    grid = Intrinsics(*truth).scaled(size.scale_x, size.scale_y).to_grid()
    starts = range(0, len(frames) - gap * (keyframes - 1), every)
    errors = []
    for start in tqdm(starts, desc=name, unit="window", leave=False):
        index = [start + gap * k for k in range(keyframes)]
        images = [resize_to_working(frames[i].rgb, size) for i in index]
        found = window_focal(images, gt.world_from_cam[index], grid, params, flow_params)
        errors.append(100.0 * (float(found[0]) / grid.fx - 1.0))
    return np.asarray(errors)


def row(name: str, errors: np.ndarray) -> list[str]:
    kept = errors[np.abs(errors) <= DIVERGED_PCT]
    if not len(kept):
        return [name, str(len(errors)), "–", "–", "–", str(len(errors))]
    q1, median, q3 = np.percentile(kept, [25, 50, 75])
    return [name, str(len(errors)), f"{median:+.2f}", f"{q1:+.2f} / {q3:+.2f}", f"{kept.mean():+.2f}",
            str(len(errors) - len(kept))]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--profiles", default="real", help="comma-separated names or groups, as bench/robustness.py")
    parser.add_argument("--keyframes", type=int, default=6, help="frames per window (the pipeline calibrates at 6)")
    parser.add_argument("--gap", type=int, default=3, help="frames between a window's keyframes")
    parser.add_argument("--every", type=int, default=10, help="frames between window starts")
    parser.add_argument("--principal-point", action="store_true", help="free the principal point too")
    add_sequence_arguments(parser)
    args = parser.parse_args()
    if args.keyframes < 2 or args.gap < 1 or args.every < 1:
        parser.error("--keyframes must be >= 2, --gap and --every >= 1")
    torch.set_num_threads(args.threads)
    setup_logging("bench-focal-evidence", LogSettings(level="ERROR"))
    settings = BaSettings()
    frontend = settings.frontend_params()
    params = dataclasses.replace(focal_ba(frontend.ba, frontend), iterations=40,
                                 optimise_principal_point=args.principal_point)
    header = ["sequence", "windows", "median focal err %", "quartiles %", "mean %", f"beyond {DIVERGED_PCT:.0f} %"]
    rows = []
    for name in (bar := tqdm(profile_names(args.profiles), unit="sequence")):
        bar.set_description(name)
        if name in REAL:
            source = str(args.data / REAL[name])
        else:
            source = str(cached_profile(name, args.frames, *args.size, args.cache.expanduser())[0])
        rows.append(row(name, sequence_errors(source, args.keyframes, args.gap, args.every, params, frontend.flow,
                                              name)))
        tqdm.write("  ".join(rows[-1]))
    if args.markdown:
        print("| " + " | ".join(header) + " |\n|" + " --- |" * len(header))
        print("\n".join("| " + " | ".join(r) + " |" for r in rows))
    else:
        widths = [max(len(h), *(len(r[i]) for r in rows)) for i, h in enumerate(header)]
        for r in [header, *rows]:
            print("  ".join(c.rjust(wd) for c, wd in zip(r, widths)))
    print(f"summary: {len(rows)} sequences, windows of {args.keyframes} frames {args.gap} apart held at the ground "
          f"truth; the focal error each window's flow supports (0 = the flow agrees with the true focal)")


if __name__ == "__main__":
    main()
