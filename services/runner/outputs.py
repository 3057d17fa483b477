"""The files a run writes at its end from what the runner saw on the bus: ``trajectory.txt`` (each frame's latest
pose), ``trajectory_live.txt`` and ``frames.csv`` (what a live consumer saw), the ATE of each against the source's
ground truth, ``camera.txt`` (the refined intrinsics) and ``summary.json``."""
from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..evaluation.trajectory_io import Trajectory, write_tum
from .groundtruth import evaluate, source_intrinsics

if TYPE_CHECKING:
    from .pipeline import RunReport


def trajectory(poses: dict[int, tuple]) -> Trajectory:
    """``seq → (..., stamp_ns, pose)`` as a trajectory in seq order."""
    seqs = sorted(poses)
    return Trajectory(np.array([poses[s][-2] for s in seqs], np.float64) / 1e9,
                      np.stack([np.asarray(poses[s][-1], np.float64) for s in seqs]))


def write_live(out: Path, first_poses: dict[int, tuple[float, int, object]], seen_at: dict[int, float],
               first_tracked: set[int], provisional: set[int]) -> list[str]:
    """What a live consumer saw: ``trajectory_live.txt`` (TUM, each frame's first pose as it was published) and
    ``frames.csv`` (per frame seen on the bus: its stamp, the latency from the frame to its first pose, and whether
    tracking or mapping gave that pose; ``provisional``: tracking's rotation-only pose from before the map)."""
    if not first_poses and not seen_at:
        return []
    written = []
    if first_poses:
        path = out / "trajectory_live.txt"
        write_tum(path, trajectory(first_poses))
        written.append(str(path))
    path = out / "frames.csv"
    with path.open("w") as csv:
        csv.write("seq,stamp_s,latency_ms,first_pose\n")
        for seq in sorted(set(seen_at) | set(first_poses)):
            first = first_poses.get(seq)
            latency = "" if first is None or seq not in seen_at else f"{max(0.0, first[0] - seen_at[seq]) * 1e3:.1f}"
            stamp = "" if first is None else f"{first[1] / 1e9:.6f}"
            source = "" if first is None else ("provisional" if seq in provisional else
                                               "tracked" if seq in first_tracked else "mapped")
            csv.write(f"{seq},{stamp},{latency},{source}\n")
    written.append(str(path))
    return written


def write_resources(out: Path, timeline: list[tuple[float, str, float, float, float | None]]) -> list[str]:
    """``resources.csv``: every sample of every service's CPU seconds, RSS and PSS (MB) since the runner started
    (``ResourceMonitor.timeline``), to see when a peak came and which service made it."""
    if not timeline:
        return []
    path = out / "resources.csv"
    with path.open("w") as csv:
        csv.write("t_s,service,cpu_s,rss_mb,pss_mb\n")
        for t_s, name, cpu_s, rss_mb, pss_mb in timeline:
            csv.write(f"{t_s},{name},{cpu_s},{rss_mb},{'' if pss_mb is None else pss_mb}\n")
    return [str(path)]


def write_camera(out: Path, source: str, report: RunReport) -> list[str]:
    """``camera.txt``: ba's refined intrinsics in the source's pixels as ``fx fy cx cy width height`` (the layout of
    the datasets' camera.txt; ``kmvipe run --intrinsics`` takes its first four), and the focal error against the
    source's true intrinsics when it has them."""
    if report.intrinsics is None:
        return []
    truth = source_intrinsics(source)
    if truth is not None and truth[0] > 0:
        report.focal_error_pct = round(100.0 * (report.intrinsics[0] / float(truth[0]) - 1.0), 3)
    path = out / "camera.txt"
    size = "" if report.image_size is None else " {} {}".format(*report.image_size)
    path.write_text(" ".join(f"{v:.3f}" for v in report.intrinsics) + size + "\n")
    return [str(path)]


def write_outputs(out: Path, source: str, report: RunReport, poses: dict[int, tuple[int, object]],
                  first_poses: dict[int, tuple[float, int, object]], provisional: set[int],
                  also_written: list[str] = ()) -> list[str]:
    """trajectory.txt (the latest pose of every frame), the ATE of those and of each frame's first pose (what a
    live consumer saw at the time) when the source has ground truth, and summary.json."""
    written = []
    if poses:
        path = out / "trajectory.txt"
        estimate = trajectory(poses)
        write_tum(path, estimate)
        written.append(str(path))
        live = trajectory(first_poses)
        placed = {seq: p for seq, p in first_poses.items() if seq not in provisional}
        more = [live] + ([trajectory(placed)] if len(placed) >= 3 and len(placed) < len(first_poses) else [])
        ate, ate_live, *ate_placed = evaluate(source, estimate, *more)
        if ate is not None:
            report.ate_rmse_sim3, report.ate_pairs = ate.rmse, ate.n_pairs
        if ate_live is not None:
            report.ate_first_poses, report.ate_first_poses_pairs = ate_live.rmse, ate_live.n_pairs
        if ate_placed and ate_placed[0] is not None:
            mapped = ate_placed[0]
            report.ate_first_poses_mapped, report.ate_first_poses_mapped_pairs = mapped.rmse, mapped.n_pairs
    written += write_camera(out, source, report)
    written += list(also_written)
    written += [str(out / name) for name in ("map.ply", "colmap/cameras.txt") if (out / name).is_file()]
    summary = out / "summary.json"
    summary.write_text(json.dumps(asdict(report) | {"outputs": written + [str(summary)]}, indent=2, default=str))
    written.append(str(summary))
    return written
