"""Drift along a trajectory: the estimate aligned once, on its first stretch, and its error stretch by stretch after.
A whole-trajectory ATE aligns on everything and spreads drift over the run; aligned on the start, the error of a
camera that comes round the same places again shows whether it returns to where it was the first time."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.evaluation.ate import matched_poses, umeyama
from services.evaluation.trajectory_io import Trajectory


@dataclass(frozen=True)
class Stretch:
    first: int  # index of its first matched pose
    count: int  # matched poses in it
    mean_error: float  # mean position error, the estimate aligned (Sim(3)) on the first stretch
    scale_ratio: float  # the estimate's scale in it over its scale in the first stretch (1: no scale drift since)


def drift_by_stretch(reference: Trajectory, estimate: Trajectory, length: int,
                     max_diff: float = 0.01) -> list[Stretch]:
    """The matched poses in consecutive stretches of ``length`` (the last may be shorter; one of fewer than 3
    poses is left out): each one's error with the estimate aligned on the first, and the estimate's scale in it
    against the first's."""
    if length < 3:
        raise ValueError(f"a stretch needs at least 3 poses to align, got length {length}")
    ref_poses, est_poses, _ = matched_poses(reference, estimate, max_diff)
    ref, est = ref_poses[:, :3, 3], est_poses[:, :3, 3]
    first = umeyama(est[:length], ref[:length], with_scale=True)
    aligned = first.scale * est @ first.rotation.T + first.translation
    error = np.linalg.norm(aligned - ref, axis=1)
    out = []
    for start in range(0, len(ref), length):
        part = slice(start, start + length)
        if len(ref[part]) < 3:
            break
        scale = umeyama(est[part], ref[part], with_scale=True).scale
        out.append(Stretch(start, len(ref[part]), float(error[part].mean()), first.scale / scale))
    return out
