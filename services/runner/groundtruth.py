"""Ground truth for a run's source, when it has one: the synthetic world's exact poses, or a
``groundtruth.txt`` (TUM format, camera-to-world) beside an image folder (TUM RGB-D, the shared KITTI set); and
its true intrinsics, from the synthetic world, a ``camera.txt`` (fx fy cx cy width height) or KITTI's
``calib.txt`` beside the folder."""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..common.errors import SourceError
from ..evaluation.ate import AteResult, absolute_trajectory_error
from ..evaluation.trajectory_io import Trajectory, TrajectoryFormatError, read_tum

log = logging.getLogger(__name__)
MAX_STAMP_DIFF_S = 0.02  # frame stamps of the estimate and the GT come from the same source


def source_groundtruth(source: str) -> Trajectory | None:
    if source.startswith("synth:"):
        from ..ingest.sources import open_source

        world = open_source(source).world
        return Trajectory(world.timestamps_ns() / 1e9, world.poses)
    gt = Path(source) / "groundtruth.txt"
    if gt.is_file():
        try:
            return read_tum(gt)
        except TrajectoryFormatError as exc:
            log.warning("groundtruth.txt beside the source is not TUM; no ATE", extra={"error": str(exc)})
    return None


def evaluate(source: str, estimate: Trajectory, *more: Trajectory) -> AteResult | None | list[AteResult | None]:
    """Sim(3)-aligned ATE of ``estimate`` against the source's ground truth, or None without one. With ``more``
    trajectories, a list with the ATE of each (the ground truth is read once)."""
    estimates = [estimate, *more]
    try:
        reference = source_groundtruth(source)
    except SourceError:
        reference = None
    results = [None if reference is None else _ate(reference, e) for e in estimates]
    return results if more else results[0]


def _ate(reference: Trajectory, estimate: Trajectory) -> AteResult | None:
    try:
        return absolute_trajectory_error(reference, estimate, align="sim3", max_diff=MAX_STAMP_DIFF_S)
    except ValueError as exc:
        log.warning("could not evaluate the trajectory", extra={"error": str(exc)})
        return None


def source_intrinsics(source: str) -> np.ndarray | None:
    """The source's true (fx, fy, cx, cy) in its pixels, or None where it has none or they do not parse."""
    try:
        if source.startswith("synth:"):
            from ..ingest.sources import open_source

            return np.asarray(open_source(source).world.intrinsics, np.float64)
        folder = Path(source)
        if (folder / "camera.txt").is_file():
            values = (folder / "camera.txt").read_text().split()
            if len(values) < 4:
                raise ValueError(f"camera.txt holds {len(values)} values, fx fy cx cy expected first")
            return np.array(values[:4], np.float64)
        if (folder / "calib.txt").is_file():  # KITTI: "P0: fx 0 cx 0 0 fy cy 0 0 0 1 0"
            p0 = (folder / "calib.txt").read_text().split()
            return np.array([p0[1], p0[6], p0[3], p0[7]], np.float64)
    except (SourceError, ValueError, IndexError) as exc:
        log.warning("the source's intrinsics do not parse; no focal error", extra={"error": str(exc)})
    return None
