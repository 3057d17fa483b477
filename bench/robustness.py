"""Motion robustness suite: hand-held motion profiles on the synthetic room, plus the real sequences.

Every profile is rendered by ``services.synth`` along an exact trajectory (``profile_poses``) and streamed through
the keyframe selector and the BA frontend as the pipeline does (``bench/frontend.py``'s ``run_frontend``), with no
calibration: the focal starts at the 60 deg prior. One row per profile: frames, posed %, ATE (Sim(3), positions) as
% of the path, the largest rotation error of any frame relative to the first (degrees; the measure for rotation-only
motion), the focal error, keyframes and seconds.

Profiles (``--profiles``, default all; frames at 30 Hz):
  rot0 (walking only),
  rot0.5, rot1, rot2, rot3   walking sideways 1 cm/frame while yawing back and forth, peak rate 0.5-3 deg/frame,
                             with a slow pitch and roll wobble
  pure_rotation              moving, then 40 frames of pure yaw at 1 deg/frame (no parallax), then moving again
  turn180                    a 180 deg turn (1.5 deg/frame) while walking 1 cm/frame
  fast_pan                   yaw back and forth at up to 4 deg/frame, 0.5 cm/frame of translation
  backwards                  walking backwards 1.5 cm/frame with a little yaw
  fov40, fov110              rot1 seen through a 40 deg and a 110 deg (horizontal) lens
  tartanair, desk, kitti     the real sequences in ../shared/data (``--real`` to include them)

Usage:
  python bench/robustness.py                          # synthetic profiles at 384x512
  python bench/robustness.py --size 640x480 --real    # 640x480, and the real sequences
  python bench/robustness.py --profiles rot1,turn180 --markdown
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parent))
from frontend import run_frontend  # noqa: E402  (bench/frontend.py, the same per-frame path)

from services.common.config import LogSettings  # noqa: E402
from services.common.logs import setup_logging  # noqa: E402
from services.evaluation.ate import absolute_trajectory_error  # noqa: E402
from services.evaluation.trajectory_io import Trajectory  # noqa: E402
from services.ingest.sources import SourceFrame, open_source  # noqa: E402
from services.runner.groundtruth import source_groundtruth  # noqa: E402
from services.synth.camera import look_at  # noqa: E402
from services.synth.config import SynthConfig  # noqa: E402
from services.synth.render import SynthWorld  # noqa: E402

FPS = 30.0
SYNTHETIC = ("rot0.5", "rot1", "rot2", "rot3", "pure_rotation", "turn180", "fast_pan", "backwards", "fov40", "fov110")
REAL = {"tartanair": "tartanair_hospital", "desk": "handheld_desk", "kitti": "kitti07_160"}
DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


@dataclass(frozen=True)
class Motion:
    """Per-frame camera motion: position (n, 3) in the room, and yaw / pitch / roll (n,) in degrees."""

    position: np.ndarray
    yaw: np.ndarray
    pitch: np.ndarray
    roll: np.ndarray


def _poses(m: Motion) -> np.ndarray:
    """world_from_cam (n, 4, 4): looking along +y at the start, yaw about world up, pitch and roll about the
    camera's own x and z axes."""
    out = np.zeros((len(m.yaw), 4, 4))
    for i, p in enumerate(m.position):
        base = look_at(p, p + np.array([0.0, 1.0, 0.0]))
        out[i] = base
        yaw = Rotation.from_euler("z", m.yaw[i], degrees=True).as_matrix()
        tilt = Rotation.from_euler("XZ", [m.pitch[i], m.roll[i]], degrees=True).as_matrix()  # intrinsic: camera x, then z
        out[i, :3, :3] = yaw @ base[:3, :3] @ tilt
    return out


def _swing(n: int, peak_rate: float, period: int) -> np.ndarray:
    """Back-and-forth angle (deg) whose rate peaks at ``peak_rate`` deg/frame."""
    return peak_rate * period / (2 * math.pi) * np.sin(2 * math.pi * np.arange(n) / period)


def _walk(n: int, step: float, direction=(1.0, 0.0, 0.0), start=(2.9, 1.4, 1.4)) -> np.ndarray:
    return np.asarray(start) + step * np.arange(n)[:, None] * np.asarray(direction)


def profile_motion(name: str, n: int = 120) -> tuple[Motion, float]:
    """The motion of a named profile and its horizontal field of view (degrees)."""
    i = np.arange(n)
    wobble_p, wobble_r = 2.0 * np.sin(2 * math.pi * i / 97), 1.5 * np.sin(2 * math.pi * i / 71 + 1.0)
    if name.startswith("rot") or name in ("fov40", "fov110"):
        rate = float(name[3:]) if name.startswith("rot") else 1.0
        fov = float(name[3:]) if name.startswith("fov") else 60.0
        return Motion(_walk(n, 0.01), _swing(n, rate, 120), wobble_p, wobble_r), fov
    if name == "pure_rotation":
        third = n // 3
        moving = np.r_[np.arange(third), np.full(third, third), third + np.arange(n - 2 * third)]
        yaw = np.r_[np.zeros(third), np.arange(third) * 1.0, np.full(n - 2 * third, third - 1.0)]
        return Motion(_walk(1, 0)[0] + 0.01 * moving[:, None] * np.array([1.0, 0, 0]), yaw, wobble_p, wobble_r), 60.0
    if name == "turn180":
        return Motion(_walk(n, 0.01, start=(3.0, 1.6, 1.4)), np.linspace(0, 180, n), wobble_p, wobble_r), 60.0
    if name == "fast_pan":
        return Motion(_walk(n, 0.005), _swing(n, 4.0, 47), wobble_p, wobble_r), 60.0
    if name == "backwards":
        return Motion(_walk(n, 0.015, (0.0, -1.0, 0.0), start=(3.5, 2.5, 1.4)), _swing(n, 0.3, 120), wobble_p,
                      wobble_r), 60.0
    raise ValueError(f"unknown profile {name!r}; known: {', '.join(SYNTHETIC)}")


def profile_poses(name: str, n: int = 120) -> tuple[np.ndarray, float]:
    motion, fov = profile_motion(name, n)
    return _poses(motion), fov


def render_profile(name: str, n: int, width: int, height: int) -> tuple[list[SourceFrame], np.ndarray, float]:
    """Frames, ground-truth poses (n, 4, 4) and the true focal (px) of a profile."""
    poses, fov = profile_poses(name, n)
    cfg = SynthConfig(n_frames=n, width=width, height=height, hfov_deg=fov, fps=FPS, person=False,
                      moved_chair=False)
    world = SynthWorld(cfg, poses=poses)
    frames = [SourceFrame(i, int(round(i * 1e9 / FPS)), world.render(i).rgb) for i in range(n)]
    return frames, poses, float(world.intrinsics[0])


@dataclass
class Row:
    profile: str
    frames: int
    posed_pct: float
    ate_pct_path: float
    max_rot_err_deg: float
    focal_err_pct: float
    keyframes: int
    seconds: float


def score(name: str, gt: Trajectory, est: Trajectory, n_frames: int, focal_true: float | None, run) -> Row:
    """ATE (Sim(3)) as % of the ground-truth path, max rotation error relative to the first frame, focal error."""
    res = absolute_trajectory_error(gt, est, align="sim3", max_diff=0.02)
    path = float(np.linalg.norm(np.diff(gt.positions, axis=0), axis=1).sum())
    g = {round(t, 3): p for t, p in zip(gt.timestamps, gt.world_from_cam)}
    pairs = [(g[round(t, 3)], p) for t, p in zip(est.timestamps, est.world_from_cam) if round(t, 3) in g]
    rel = [(np.linalg.inv(pairs[0][0]) @ a, np.linalg.inv(pairs[0][1]) @ b) for a, b in pairs]
    cos = [(np.trace(a[:3, :3].T @ b[:3, :3]) - 1) / 2 for a, b in rel]
    rot_err = float(np.degrees(np.arccos(np.clip(min(cos), -1, 1))))
    focal_err = float("nan") if focal_true is None else 100 * abs(run.focal_px - focal_true) / focal_true
    return Row(name, n_frames, 100 * len(run.latest) / n_frames, 100 * res.rmse / max(path, 1e-9), rot_err, focal_err,
               run.keyframes, run.wall_seconds)


def run_synthetic(name: str, n: int, width: int, height: int) -> Row:
    frames, poses, focal = render_profile(name, n, width, height)
    run = run_frontend(frames, progress=False)
    stamps = np.array([f.t_ns for f in frames]) / 1e9
    return score(name, Trajectory(stamps, poses), run.trajectory(), n, focal, run)


def run_real(name: str) -> Row:
    folder = DATA / REAL[name]
    frames = [f for f in open_source(str(folder)).frames() if isinstance(f, SourceFrame)]
    run = run_frontend(frames, progress=False)
    return score(name, source_groundtruth(str(folder)), run.trajectory(), len(frames), _true_focal(folder), run)


def _true_focal(folder: Path) -> float | None:
    """fx from ``camera.txt`` (fx fy cx cy w h) or KITTI's ``calib.txt`` (P0: fx 0 cx ...)."""
    if (folder / "camera.txt").is_file():
        return float((folder / "camera.txt").read_text().split()[0])
    if (folder / "calib.txt").is_file():
        return float((folder / "calib.txt").read_text().split()[1])
    return None


def table(rows: list[Row], markdown: bool) -> str:
    head = ("profile", "frames", "posed %", "ATE % path", "max rot err deg", "focal err %", "keyframes", "s")
    lines = [" | ".join(head), " | ".join("---" for _ in head)] if markdown else ["  ".join(f"{h:>15}" for h in head)]
    for r in rows:
        cells = (r.profile, str(r.frames), f"{r.posed_pct:.1f}", f"{r.ate_pct_path:.2f}", f"{r.max_rot_err_deg:.2f}",
                 f"{r.focal_err_pct:.1f}", str(r.keyframes), f"{r.seconds:.0f}")
        lines.append(" | ".join(cells) if markdown else "  ".join(f"{c:>15}" for c in cells))
    return "\n".join(("| " + ln + " |") if markdown else ln for ln in lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--profiles", default=",".join(SYNTHETIC), help="comma-separated profile names")
    parser.add_argument("--size", default="384x512", help="HEIGHTxWIDTH for 384x512, WIDTHxHEIGHT for 640x480")
    parser.add_argument("--frames", type=int, default=120)
    parser.add_argument("--real", action="store_true", help="add tartanair, desk and kitti from ../shared/data")
    parser.add_argument("--markdown", action="store_true")
    args = parser.parse_args()
    torch.set_num_threads(1)
    setup_logging("bench-robustness", LogSettings(level="ERROR"))
    a, b = (int(v) for v in args.size.lower().split("x"))
    width, height = max(a, b), min(a, b)  # both sizes named in the issue are landscape
    names = [p for p in args.profiles.split(",") if p]
    if args.real:
        names += list(REAL)
    rows = []
    for k, name in enumerate(names):
        t0 = time.perf_counter()
        row = run_real(name) if name in REAL else run_synthetic(name, args.frames, width, height)
        rows.append(row)
        print(f"[{k + 1}/{len(names)}] {name}: ATE {row.ate_pct_path:.2f} % of path, posed {row.posed_pct:.0f} %, "
              f"focal error {row.focal_err_pct:.1f} % ({time.perf_counter() - t0:.0f} s)", flush=True)
    print(table(rows, args.markdown))
    failing = [r.profile for r in rows if r.ate_pct_path > 1.0 or r.posed_pct < 100.0]
    print(f"summary: {len(rows) - len(failing)}/{len(rows)} profiles within 1 % of path with every frame posed"
          + (f"; over: {', '.join(failing)}" if failing else ""))


if __name__ == "__main__":
    main()
