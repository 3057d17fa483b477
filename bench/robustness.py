"""Motion robustness suite (issue 13): hand-held motion profiles in the synthetic room, plus the real sequences.

Every synthetic profile (``services/synth/profiles.py``: yaw at 0.5-3 °/frame while walking, pure rotation, a
180° turn, fast pans, walking backwards, a bare wall, 40-110° lenses) is rendered once into an image folder in the
same layout as ``../shared/data`` (``rgb/``, ``rgb.txt``, ``groundtruth.txt``, ``camera.txt``) under ``--cache``, so
re-runs skip the renderer and ``kmvipe run FOLDER`` plays the same frames. Every profile and real sequence is then
streamed through the keyframe selector and the BA frontend as the pipeline does (``bench/frontend.py``'s
``run_frontend``), with no calibration: the focal starts at the 60° prior.

One row per profile: frames, posed %, ATE (Sim(3) aligned, positions) as % of the ground-truth path, the largest
rotation error of any frame relative to the first, the rotation error inside a rotation-only stretch (the measure
where there is no path: ``spin``, and ``pure_rotation``'s middle third), the focal error, keyframes, seconds.

Usage:
  python bench/robustness.py                                   # every profile at 384x512, then the real sequences
  python bench/robustness.py --profiles synthetic --size 640x480 --markdown
  python bench/robustness.py --profiles rot1,turn180,tartanair --frames 60
"""
from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
from frontend import FrontendRun, run_frontend  # noqa: E402  (bench/frontend.py: the same per-frame path)

from services.common.config import LogSettings  # noqa: E402
from services.common.logs import setup_logging  # noqa: E402
from services.evaluation.ate import absolute_trajectory_error  # noqa: E402
from services.evaluation.trajectory_io import Trajectory, write_tum  # noqa: E402
from services.ingest.sources import SourceFrame, open_source  # noqa: E402
from services.runner.groundtruth import source_groundtruth, source_intrinsics  # noqa: E402
from services.synth.profiles import SYNTHETIC, Profile, profile, profile_world  # noqa: E402

FPS = 30.0  # hand-held video rate: the per-frame rates of the profiles are per 1/30 s
REAL = {"tartanair": "tartanair_hospital", "desk": "handheld_desk", "kitti": "kitti07_160"}
# Frames whose ground truth is the camera's pose in the static world. The desk's GT is checkerboard PnP, and a hand
# moves the board in frames ~378-620 (bench/data/desk_board_motion.py): there the GT follows the board while the
# system, which leaves moved objects out, follows the desk. Its extra row scores the frames before that.
STILL_GT = {"desk": (0, 375)}
GROUPS = {"synthetic": SYNTHETIC, "real": tuple(REAL)}
CACHE_FORMAT = 1  # bump when the folder layout or the renderer's output changes, so old caches re-render
TARGET_ATE_PCT = 1.0  # issue 13's acceptance: every synthetic profile within 1 % of its path, all frames posed
MATCH_S = 0.02  # timestamp association for ATE, seconds (frames are >= 33 ms apart)


def default_cache() -> Path:
    return Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "kmvipe" / "robustness"


def default_data() -> Path:
    return Path(__file__).resolve().parents[1].parent / "shared" / "data"


def _fingerprint(p: Profile, width: int, height: int) -> str:
    """Everything the rendered frames depend on; a cached folder with another fingerprint is rendered again."""
    h = hashlib.sha256(np.ascontiguousarray(p.poses).tobytes())
    h.update(json.dumps([CACHE_FORMAT, p.hfov_deg, p.wall_contrast, width, height, FPS]).encode())
    return h.hexdigest()[:16]


def cached_profile(name: str, n: int, width: int, height: int, cache: Path) -> tuple[Path, Profile]:
    """The image folder of profile ``name`` (rendered into ``cache`` if missing or stale) and the profile."""
    p = profile(name, n)
    folder = cache / f"{name}-{width}x{height}-{n}"
    stamp = _fingerprint(p, width, height)
    meta = folder / "profile.json"
    if meta.is_file() and json.loads(meta.read_text()).get("fingerprint") == stamp:
        return folder, p
    tmp = folder.with_name(folder.name + ".partial")  # renamed when complete: an interrupted render is not a cache
    shutil.rmtree(tmp, ignore_errors=True)
    (tmp / "rgb").mkdir(parents=True)
    world = profile_world(p, width, height, FPS)
    lines = ["# timestamp filename"]
    for i in tqdm(range(n), desc=f"render {name}", unit="frame", leave=False):
        cv2.imwrite(str(tmp / "rgb" / f"{i:06d}.png"), world.render(i).rgb[..., ::-1])
        lines.append(f"{world.t_ns(i) / 1e9:.9f} rgb/{i:06d}.png")
    (tmp / "rgb.txt").write_text("\n".join(lines) + "\n")
    write_tum(tmp / "groundtruth.txt", Trajectory(world.timestamps_ns() / 1e9, p.poses))
    fx, fy, cx, cy = world.intrinsics
    (tmp / "camera.txt").write_text(f"{fx:.6f} {fy:.6f} {cx:.6f} {cy:.6f} {width} {height}\n")
    (tmp / "profile.json").write_text(json.dumps({"fingerprint": stamp, "profile": name, "frames": n,
                                                  "hfov_deg": p.hfov_deg, "wall_contrast": p.wall_contrast,
                                                  "rotation_only": p.rotation_only, "fps": FPS}, indent=1))
    shutil.rmtree(folder, ignore_errors=True)
    tmp.rename(folder)
    return folder, p


@dataclass
class Row:
    profile: str
    frames: int
    posed_pct: float
    ate_pct_path: float  # nan where there is no path (rotation only)
    max_rot_err_deg: float  # largest rotation error of any frame relative to the first frame
    rot_only_err_deg: float  # the same inside the rotation-only stretch; nan where there is none
    focal_err_pct: float  # nan where the true focal is unknown
    keyframes: int
    seconds: float

    @property
    def passes(self) -> bool:
        within = self.ate_pct_path <= TARGET_ATE_PCT if not math.isnan(self.ate_pct_path) else True
        return within and self.posed_pct >= 100.0


def _paired(gt: Trajectory, est: Trajectory) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ground-truth and estimated world_from_cam (m, 4, 4) of the frames with both, and their gt indices (m,)."""
    idx = np.searchsorted(gt.timestamps, est.timestamps).clip(1, len(gt.timestamps) - 1)
    idx = np.where(np.abs(gt.timestamps[idx - 1] - est.timestamps) < np.abs(gt.timestamps[idx] - est.timestamps),
                   idx - 1, idx)
    ok = np.abs(gt.timestamps[idx] - est.timestamps) <= MATCH_S
    return gt.world_from_cam[idx[ok]], est.world_from_cam[ok], idx[ok]


def max_rotation_error(gt: np.ndarray, est: np.ndarray) -> float:
    """Largest angle (degrees) between the estimated and true rotations of any frame relative to the first frame,
    over paired world_from_cam (m, 4, 4): what a Sim(3) alignment cannot hide, and the measure without a path."""
    if len(gt) < 2:
        return float("nan")
    rel_gt = np.linalg.inv(gt[0])[:3, :3] @ gt[:, :3, :3]
    rel_est = np.linalg.inv(est[0])[:3, :3] @ est[:, :3, :3]
    cos = (np.einsum("nji,nji->n", rel_gt, rel_est) - 1) / 2  # trace(A^T B)
    return float(np.degrees(np.arccos(np.clip(cos, -1, 1))).max())


def score(name: str, gt: Trajectory, est: Trajectory, n_frames: int, focal_true: float | None, run: FrontendRun,
          rotation_only: tuple[int, int] | None = None, posed: int | None = None) -> Row:
    """The row of one run: ``est`` is ``run``'s trajectory (bench/ablation_kernel.py passes its own); ``posed``:
    frames posed of the ``n_frames`` (default: every pose the run gave)."""
    g, e, idx = _paired(gt, est)
    path = float(np.linalg.norm(np.diff(gt.positions, axis=0), axis=1).sum())
    ate = float("nan")
    if path > 1e-6 and len(e) >= 3:
        ate = 100 * absolute_trajectory_error(gt, est, align="sim3", max_diff=MATCH_S).rmse / path
    seg = float("nan")
    if rotation_only is not None:
        inside = (idx >= rotation_only[0]) & (idx < rotation_only[1])
        seg = max_rotation_error(g[inside], e[inside])
    focal = float("nan") if focal_true is None else 100 * abs(run.focal_px - focal_true) / focal_true
    posed = len(run.latest) if posed is None else posed
    return Row(name, n_frames, 100 * posed / n_frames, ate, max_rotation_error(g, e), seg, focal,
               run.keyframes, run.wall_seconds)


def true_focal(folder: Path) -> float | None:
    """fx of the folder's true intrinsics (``camera.txt`` or KITTI's ``calib.txt``), None without them."""
    truth = source_intrinsics(str(folder))
    return None if truth is None else float(truth[0])


def run_folder(name: str, folder: Path, rotation_only: tuple[int, int] | None = None) -> list[Row]:
    """One image folder with ``groundtruth.txt`` through the frontend, no calibration given: its row, and one for
    the frames of ``STILL_GT`` where only part of the ground truth is the camera in the static world."""
    frames = [f for f in open_source(str(folder)).frames() if isinstance(f, SourceFrame)]
    run = run_frontend(frames, progress=True)
    gt, est = source_groundtruth(str(folder)), run.trajectory()
    rows = [score(name, gt, est, len(frames), true_focal(folder), run, rotation_only)]
    if name in STILL_GT:
        first, end = STILL_GT[name]
        t0, t1 = gt.timestamps[first] - MATCH_S, gt.timestamps[end - 1] + MATCH_S
        inside = (est.timestamps >= t0) & (est.timestamps <= t1)
        rows.append(score(f"{name} {first}-{end - 1}", Trajectory(gt.timestamps[first:end], gt.world_from_cam[first:end]),
                          Trajectory(est.timestamps[inside], est.world_from_cam[inside]), end - first,
                          true_focal(folder), run, posed=int(inside.sum())))
    return rows


def profile_poses(name: str, n: int = 120) -> tuple[np.ndarray, float]:
    """world_from_cam (n, 4, 4) and horizontal fov (degrees) of a profile (bench/ablation_kernel.py renders them)."""
    p = profile(name, n)
    return p.poses, p.hfov_deg


def run_profile(name: str, n: int, width: int, height: int, cache: Path) -> Row:
    folder, p = cached_profile(name, n, width, height, cache)
    return run_folder(name, folder, p.rotation_only)[0]


def _cell(value: float, fmt: str) -> str:
    return "–" if math.isnan(value) else format(value, fmt)


def table(rows: list[Row], markdown: bool) -> str:
    head = ("profile", "frames", "posed %", "ATE % path", "max rot err °", "rot-only err °", "focal err %",
            "keyframes", "s")
    body = [(r.profile, str(r.frames), f"{r.posed_pct:.1f}", _cell(r.ate_pct_path, ".2f"),
             _cell(r.max_rot_err_deg, ".2f"), _cell(r.rot_only_err_deg, ".2f"), _cell(r.focal_err_pct, ".1f"),
             str(r.keyframes), f"{r.seconds:.0f}") for r in rows]
    if markdown:
        return "\n".join("| " + " | ".join(cells) + " |" for cells in [head, ["---"] * len(head), *body])
    width = max(len(h) for h in head)
    return "\n".join("  ".join(f"{c:>{width}}" for c in cells) for cells in [head, *body])


def summary(rows: list[Row]) -> str:
    synthetic = [r for r in rows if r.profile.split()[0] not in REAL]  # "desk 0-374" is the desk's
    over = [r.profile for r in synthetic if not r.passes]
    line = (f"summary: {len(synthetic) - len(over)}/{len(synthetic)} synthetic profiles within "
            f"{TARGET_ATE_PCT:g} % of path with every frame posed")
    return line + (f"; over: {', '.join(over)}" if over else "")


def profile_names(spec: str) -> list[str]:
    """``synthetic,real`` / ``rot1,kitti`` → profile names (groups expanded, order kept, checked)."""
    names: list[str] = []
    for item in filter(None, (s.strip() for s in spec.split(","))):
        for name in GROUPS.get(item, (item,)):
            if name not in REAL:
                profile(name, 3)  # raises, naming the known profiles
            if name not in names:
                names.append(name)
    return names


def parse_size(text: str) -> tuple[int, int]:
    """``384x512`` or ``640x480`` → (width, height): both sizes the issue names are landscape."""
    try:
        a, b = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must be like 384x512 or 640x480, got {text!r}") from None
    return max(a, b), min(a, b)


def add_sequence_arguments(parser: argparse.ArgumentParser) -> None:
    """The options that say where the profiles and real sequences come from, and how results are printed (shared
    with bench/focal_evidence.py)."""
    parser.add_argument("--size", type=parse_size, default=(512, 384), help="synthetic frame size, e.g. 640x480")
    parser.add_argument("--frames", type=int, default=120, help="frames per synthetic profile (30 Hz)")
    parser.add_argument("--cache", type=Path, default=default_cache(), help="rendered profiles (image folders)")
    parser.add_argument("--data", type=Path, default=default_data(), help="folder with the real sequences")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    parser.add_argument("--markdown", action="store_true", help="print the table as markdown")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--profiles", default="synthetic,real",
                        help=f"comma-separated names or groups (synthetic: {', '.join(SYNTHETIC)}; "
                             f"real: {', '.join(REAL)})")
    add_sequence_arguments(parser)
    args = parser.parse_args()
    names = profile_names(args.profiles)
    torch.set_num_threads(args.threads)
    setup_logging("bench-robustness", LogSettings(level="ERROR"))
    width, height = args.size
    rows: list[Row] = []
    for name in (bar := tqdm(names, unit="profile")):
        bar.set_description(name)
        t0 = time.perf_counter()
        if name in REAL:
            new_rows = run_folder(name, args.data / REAL[name])
        else:
            new_rows = [run_profile(name, args.frames, width, height, args.cache.expanduser())]
        rows += new_rows
        for row in new_rows:
                tqdm.write(f"{row.profile}: posed {row.posed_pct:.0f} %, ATE {_cell(row.ate_pct_path, '.2f')} % of path, max rot "
                       f"err {_cell(row.max_rot_err_deg, '.2f')}°, focal err {_cell(row.focal_err_pct, '.1f')} % "
                       f"({time.perf_counter() - t0:.0f} s)")
    print(table(rows, args.markdown))
    print(summary(rows))


if __name__ == "__main__":
    main()
