"""Absolute trajectory error: timestamp association, Umeyama SE(3)/Sim(3) alignment, statistics (numpy).
The relative pose error over the same association and alignment is in :mod:`services.evaluation.rpe`.

Reproduces ``evo_ape <fmt> GT EST [-a | -as] --t_max_diff D`` (evo 1.38, pose relation = translation part):
association is evo's ``nearest_time`` rule, alignment maps the estimate onto the reference.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.evaluation.trajectory_io import Trajectory

ALIGNMENTS = ("se3", "sim3", "none")


@dataclass(frozen=True)
class Association:
    """Index pairs of matched poses."""

    reference_index: np.ndarray  # (M,) int
    estimate_index: np.ndarray  # (M,) int


@dataclass(frozen=True)
class Alignment:
    """``aligned = scale * rotation @ p + translation`` (estimate frame -> reference frame)."""

    rotation: np.ndarray  # (3, 3)
    translation: np.ndarray  # (3,)
    scale: float

    def apply(self, poses: np.ndarray) -> np.ndarray:
        """``world_from_cam`` poses ``(N, 4, 4)`` of the estimate in the reference frame: positions mapped as
        points, orientations rotated (evo's ``align``: scale the positions, then left-multiply the SE(3) part)."""
        out = poses.copy()
        out[:, :3, :3] = self.rotation @ poses[:, :3, :3]
        out[:, :3, 3] = self.scale * poses[:, :3, 3] @ self.rotation.T + self.translation
        return out


@dataclass(frozen=True)
class ErrorStats:
    """Statistics of per-pair errors (evo's ``get_all_statistics``; ``std`` is the population std)."""

    rmse: float
    mean: float
    median: float
    std: float
    min: float
    max: float
    sse: float
    n: int

    @classmethod
    def of(cls, errors: np.ndarray) -> ErrorStats:
        """Statistics of ``errors`` ``(P,)``, P >= 1."""
        e = np.asarray(errors, dtype=np.float64)
        return cls(rmse=float(np.sqrt(np.mean(e**2))), mean=float(e.mean()), median=float(np.median(e)),
                   std=float(e.std()), min=float(e.min()), max=float(e.max()), sse=float((e**2).sum()), n=len(e))


@dataclass(frozen=True)
class AteResult:
    """Position errors after alignment, metres (or the reference's unit)."""

    rmse: float
    mean: float
    median: float
    std: float
    min: float
    max: float
    sse: float
    n_pairs: int
    alignment: Alignment
    errors: np.ndarray  # (M,) per-pair position error


def associate(reference: np.ndarray, estimate: np.ndarray, max_diff: float) -> Association:
    """evo's nearest-time association of two timestamp arrays ``(N,)``, ``(M,)`` (seconds).

    For every stamp of the array with fewer entries (the estimate on a tie), the nearest stamp of the other is
    taken (first on ties) and the pair kept when ``|dt| <= max_diff``; a pose of the longer one can be reused.
    """
    ref_longer = len(reference) >= len(estimate)
    short, long_ = (estimate, reference) if ref_longer else (reference, estimate)
    order = np.argsort(long_, kind="stable")
    sorted_long = long_[order]
    pos = np.clip(np.searchsorted(sorted_long, short), 1, max(len(long_) - 1, 1))
    left, right = order[pos - 1], order[np.minimum(pos, len(long_) - 1)]
    d_left, d_right = np.abs(long_[left] - short), np.abs(long_[right] - short)
    # argmin semantics: on a tie evo keeps the lower index
    pick = np.where((d_left < d_right) | ((d_left == d_right) & (left < right)), left, right)
    keep = np.abs(long_[pick] - short) <= max_diff
    short_idx, long_idx = np.nonzero(keep)[0], pick[keep]
    if ref_longer:
        return Association(reference_index=long_idx, estimate_index=short_idx)
    return Association(reference_index=short_idx, estimate_index=long_idx)


def umeyama(source: np.ndarray, target: np.ndarray, with_scale: bool) -> Alignment:
    """Least-squares similarity (Umeyama 1991) mapping points ``source (M, 3)`` onto ``target (M, 3)``."""
    if source.shape != target.shape or source.ndim != 2 or source.shape[1] != 3 or len(source) < 3:
        raise ValueError(f"need matching (M>=3, 3) point sets, got {source.shape} and {target.shape}")
    mu_s, mu_t = source.mean(0), target.mean(0)
    sc, tc = source - mu_s, target - mu_t
    var_s = (sc**2).sum(1).mean()
    cov = tc.T @ sc / len(source)
    u, d, vt = np.linalg.svd(cov)
    s = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        s[2, 2] = -1
    rot = u @ s @ vt
    scale = float(np.trace(np.diag(d) @ s) / var_s) if with_scale else 1.0
    return Alignment(rotation=rot, translation=mu_t - scale * rot @ mu_s, scale=scale)


def matched_poses(reference: Trajectory, estimate: Trajectory,
                  max_diff: float) -> tuple[np.ndarray, np.ndarray, Association]:
    """The associated ``world_from_cam`` poses ``(M, 4, 4)`` of both trajectories (ValueError with fewer than 3)."""
    pairs = associate(reference.timestamps, estimate.timestamps, max_diff)
    if len(pairs.reference_index) < 3:
        raise ValueError(f"only {len(pairs.reference_index)} pose pairs within {max_diff} s; need >= 3")
    return (reference.world_from_cam[pairs.reference_index], estimate.world_from_cam[pairs.estimate_index], pairs)


def align_poses(estimate: np.ndarray, reference: np.ndarray, align: str) -> Alignment:
    """The alignment ``se3|sim3|none`` of matched positions ``estimate`` onto ``reference`` ``(M, 3)``."""
    if align not in ALIGNMENTS:
        raise ValueError(f"align must be one of {ALIGNMENTS}, got {align!r}")
    if align == "none":
        return Alignment(np.eye(3), np.zeros(3), 1.0)
    return umeyama(estimate, reference, with_scale=align == "sim3")


def absolute_trajectory_error(reference: Trajectory, estimate: Trajectory, align: str = "se3",
                              max_diff: float = 0.01) -> AteResult:
    """ATE of ``estimate`` against ``reference`` after association and alignment (``se3|sim3|none``)."""
    if align not in ALIGNMENTS:
        raise ValueError(f"align must be one of {ALIGNMENTS}, got {align!r}")
    ref_poses, est_poses, _ = matched_poses(reference, estimate, max_diff)
    ref, est = ref_poses[:, :3, 3], est_poses[:, :3, 3]
    alignment = align_poses(est, ref, align)
    aligned = alignment.scale * est @ alignment.rotation.T + alignment.translation
    err = np.linalg.norm(aligned - ref, axis=1)
    stats = ErrorStats.of(err)
    return AteResult(rmse=stats.rmse, mean=stats.mean, median=stats.median, std=stats.std, min=stats.min,
                     max=stats.max, sse=stats.sse, n_pairs=stats.n, alignment=alignment, errors=err)
