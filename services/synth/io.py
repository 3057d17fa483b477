"""Writers (adapters around the pure renderer): a TUM RGB-D style image folder and a video file.

TUM layout written by :func:`write_image_folder`::

    out_dir/rgb/<t>.png       colour, 8-bit
    out_dir/depth/<t>.png     depth, 16-bit, value = metres × 5000 (TUM's factor), 0 = missing/too far
    out_dir/rgb.txt           "<t> rgb/<t>.png" per line
    out_dir/depth.txt         "<t> depth/<t>.png" per line
    out_dir/groundtruth.txt   "<t> tx ty tz qx qy qz qw": world_from_cam (camera-to-world), Hamilton x y z w

``<t>`` is the timestamp in seconds with 6 decimals (exact integer formatting of t_ns).
"""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np

from services.evaluation import trajectory_io
from services.synth.render import SynthWorld

log = logging.getLogger(__name__)

TUM_DEPTH_FACTOR = 5000.0  # depth png value per metre, as in the TUM RGB-D benchmark
TUM_STAMP_DECIMALS = 6  # the TUM RGB-D benchmark's file names: microseconds
VIDEO_FOURCC = {".mp4": "mp4v", ".avi": "MJPG"}


def tum_timestamp(t_ns: int) -> str:
    """Seconds with 6 decimals, e.g. 1500000000 ns -> '1.500000' (exact, no float rounding)."""
    return trajectory_io.tum_timestamp(t_ns, TUM_STAMP_DECIMALS)


def depth_to_png16(depth: np.ndarray) -> np.ndarray:
    """Depth (H, W) metres -> (H, W) uint16 at TUM_DEPTH_FACTOR per metre; out-of-range becomes 0 (missing)."""
    scaled = np.round(np.asarray(depth, np.float64) * TUM_DEPTH_FACTOR)
    scaled[(scaled > np.iinfo(np.uint16).max) | ~np.isfinite(scaled) | (scaled < 0)] = 0
    return scaled.astype(np.uint16)


def write_image_folder(world: SynthWorld, out_dir: str | Path, n_frames: int | None = None) -> Path:
    """Render the first ``n_frames`` frames (all when None) into a TUM RGB-D style folder; returns it."""
    out = Path(out_dir)
    (out / "rgb").mkdir(parents=True, exist_ok=True)
    (out / "depth").mkdir(parents=True, exist_ok=True)
    count = len(world) if n_frames is None else min(int(n_frames), len(world))
    rgb_lines = ["# color images", "# timestamp filename"]
    depth_lines = ["# depth maps", f"# timestamp filename (16-bit png, {TUM_DEPTH_FACTOR:g} per metre)"]
    stamps, poses = [], []
    for i in range(count):
        frame = world.render(i)
        stamp = tum_timestamp(frame.t_ns)
        if not cv2.imwrite(str(out / "rgb" / f"{stamp}.png"), cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2BGR)):
            raise OSError(f"could not write {out / 'rgb' / stamp}.png")
        if not cv2.imwrite(str(out / "depth" / f"{stamp}.png"), depth_to_png16(frame.depth)):
            raise OSError(f"could not write {out / 'depth' / stamp}.png")
        rgb_lines.append(f"{stamp} rgb/{stamp}.png")
        depth_lines.append(f"{stamp} depth/{stamp}.png")
        stamps.append(stamp)
        poses.append(frame.world_from_cam)
    for name, lines in (("rgb.txt", rgb_lines), ("depth.txt", depth_lines)):
        (out / name).write_text("\n".join(lines) + "\n")
    (out / "groundtruth.txt").write_text(trajectory_io.tum_text(stamps, np.reshape(poses, (-1, 4, 4)),
                                                                "ground truth, " + trajectory_io.TUM_COMMENT))
    log.info("wrote %d frames to %s", count, out)
    return out


def write_video(world: SynthWorld, path: str | Path, fps: float | None = None, n_frames: int | None = None) -> Path:
    """Render frames into a video: ``.mp4`` (mp4v) or ``.avi`` (MJPG); fps defaults to the world's."""
    path = Path(path)
    fourcc = VIDEO_FOURCC.get(path.suffix.lower())
    if fourcc is None:
        raise ValueError(f"video extension must be one of {sorted(VIDEO_FOURCC)}, got {path.suffix!r}")
    path.parent.mkdir(parents=True, exist_ok=True)
    cfg = world.config
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), float(fps or cfg.fps),
                             (cfg.width, cfg.height))
    if not writer.isOpened():
        raise OSError(f"cv2.VideoWriter cannot open {path} with fourcc {fourcc}")
    count = len(world) if n_frames is None else min(int(n_frames), len(world))
    try:
        for i in range(count):
            writer.write(cv2.cvtColor(world.render(i).rgb, cv2.COLOR_RGB2BGR))
    finally:
        writer.release()
    log.info("wrote %d frames to %s", count, path)
    return path
