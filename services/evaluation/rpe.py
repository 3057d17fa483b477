"""Relative pose error as evo defines it (``evo.core.metrics.RPE``, pair selection of ``evo.core.filters``; numpy).

For index pairs ``(i, j)`` of matched poses — reference ``Q`` and estimate ``P``, both ``world_from_cam`` — the error
pose is ``E = (Q_i⁻¹ Q_j)⁻¹ (P_i⁻¹ P_j)`` (the TUM RGB-D benchmark's RPE); its translation part is ``‖t(E)‖``
(reference units) and its rotation part the angle of ``R(E)`` (degrees). Pairs are ``delta`` apart, chosen on the
estimate (evo's default, after alignment: ``evo_rpe`` aligns before it pairs):

- ``frames``, consecutive: indices ``0, δ, 2δ, …``, each pair one step of that list;
- ``frames``, all pairs: ``(i, i + δ)`` for every ``i``;
- ``m`` (path length travelled), consecutive: from index 0, the next index once the path since the last one reaches
  ``δ``; all pairs: for every ``i`` the ``j > i`` whose path length from ``i`` is nearest ``δ``, kept within
  ``rel_tol · δ``.

The trajectory-level entry (:func:`trajectory_rpe`) associates and aligns exactly as the ATE does, so
``evo_rpe tum GT EST [-a | -as] --delta D --delta_unit {f,m} [--all_pairs] --t_max_diff T`` with ``-r trans_part``
and ``-r angle_deg`` gives :attr:`RpeResult.translation` and :attr:`RpeResult.rotation`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.evaluation.ate import Alignment, ErrorStats, align_poses, matched_poses
from services.evaluation.trajectory_io import Trajectory

DELTA_UNITS = ("frames", "m")


@dataclass(frozen=True)
class RpeResult:
    """Relative pose errors of one pair selection."""

    translation: ErrorStats  # ‖t(E)‖, reference units (metres)
    rotation: ErrorStats  # angle of R(E), degrees
    translation_errors: np.ndarray  # (P,)
    rotation_errors_deg: np.ndarray  # (P,)
    pairs: np.ndarray  # (P, 2) int, indices into the matched pose arrays
    delta: float
    delta_unit: str
    all_pairs: bool


@dataclass(frozen=True)
class TrajectoryRpe:
    """RPE of an estimate against a reference after association and alignment."""

    rpe: RpeResult
    alignment: Alignment
    n_matched: int


def pair_indices(positions: np.ndarray, delta: float, delta_unit: str = "frames", all_pairs: bool = False,
                 rel_tol: float = 0.1) -> np.ndarray:
    """Index pairs ``(P, 2)`` of poses ``delta`` apart along ``positions`` ``(N, 3)`` (module docstring);
    ValueError for a bad delta or when no pair qualifies."""
    if delta_unit not in DELTA_UNITS:
        raise ValueError(f"delta_unit must be one of {DELTA_UNITS}, got {delta_unit!r}")
    if delta <= 0 or (delta_unit == "frames" and float(delta) != int(delta)):
        raise ValueError(f"delta must be > 0 (a whole number of frames for 'frames'), got {delta:g}")
    n = len(positions)
    if delta_unit == "frames":
        step = int(delta)
        if all_pairs:
            first = np.arange(max(n - step, 0))
            pairs = np.stack([first, first + step], axis=1)
        else:
            ids = np.arange(0, n, step)
            pairs = np.stack([ids[:-1], ids[1:]], axis=1)
    else:
        steps = np.linalg.norm(np.diff(positions, axis=0), axis=1)
        if all_pairs:
            pairs = _path_pairs_all(np.concatenate([[0.0], np.cumsum(steps)]), delta, rel_tol * delta)
        else:
            pairs = _path_pairs_consecutive(steps, delta)
    if len(pairs) == 0:
        raise ValueError(f"delta {delta:g} {delta_unit} gives no pose pair among {n} poses; use a smaller delta")
    return pairs.astype(np.int64).reshape(-1, 2)


def _path_pairs_consecutive(steps: np.ndarray, delta: float) -> np.ndarray:
    ids, travelled = [0], 0.0
    for i, step in enumerate(steps, start=1):
        travelled += step  # summed step by step and reset, as evo does: the overshoot is not carried over
        if travelled >= delta:
            ids.append(i)
            travelled = 0.0
    return np.stack([ids[:-1], ids[1:]], axis=1) if len(ids) > 1 else np.zeros((0, 2))


def _path_pairs_all(path: np.ndarray, delta: float, tol: float) -> np.ndarray:
    pairs = []
    for i in range(len(path) - 1):
        miss = np.abs(path[i + 1:] - path[i] - delta)
        k = int(np.argmin(miss))  # the first on ties, as evo
        if miss[k] <= tol:
            pairs.append((i, i + 1 + k))
    return np.asarray(pairs).reshape(-1, 2)


def _inverse_se3(poses: np.ndarray) -> np.ndarray:
    inv = np.zeros_like(poses)
    rot_t = np.swapaxes(poses[..., :3, :3], -1, -2)
    inv[..., :3, :3] = rot_t
    inv[..., :3, 3] = -np.einsum("...ij,...j->...i", rot_t, poses[..., :3, 3])
    inv[..., 3, 3] = 1.0
    return inv


def rotation_angles(rotations: np.ndarray) -> np.ndarray:
    """Rotation angles (radians, in [0, π]) of ``rotations`` ``(P, 3, 3)``: atan2 of the axis part and the trace
    part, accurate at small angles where ``arccos((tr − 1) / 2)`` is not."""
    skew = rotations - np.swapaxes(rotations, -1, -2)
    sin = 0.5 * np.linalg.norm(np.stack([skew[:, 2, 1], skew[:, 0, 2], skew[:, 1, 0]], axis=1), axis=1)
    cos = 0.5 * (np.trace(rotations, axis1=1, axis2=2) - 1.0)
    return np.arctan2(sin, cos)


def relative_error_poses(reference: np.ndarray, estimate: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """``E = (Q_i⁻¹ Q_j)⁻¹ (P_i⁻¹ P_j)`` ``(P, 4, 4)`` for ``pairs`` ``(P, 2)`` of poses ``(N, 4, 4)``."""
    i, j = pairs[:, 0], pairs[:, 1]
    ref_rel = _inverse_se3(reference[i]) @ reference[j]
    est_rel = _inverse_se3(estimate[i]) @ estimate[j]
    return _inverse_se3(ref_rel) @ est_rel


def relative_pose_error(reference: np.ndarray, estimate: np.ndarray, delta: float = 1, delta_unit: str = "frames",
                        all_pairs: bool = False, rel_tol: float = 0.1) -> RpeResult:
    """RPE of matched ``world_from_cam`` poses ``reference`` and ``estimate`` ``(N, 4, 4)`` (already aligned)."""
    if reference.shape != estimate.shape or reference.ndim != 3 or reference.shape[1:] != (4, 4):
        raise ValueError(f"need matching (N, 4, 4) pose arrays, got {reference.shape} and {estimate.shape}")
    pairs = pair_indices(estimate[:, :3, 3], delta, delta_unit, all_pairs, rel_tol)
    err = relative_error_poses(reference, estimate, pairs)
    trans = np.linalg.norm(err[:, :3, 3], axis=1)
    rot = np.degrees(rotation_angles(err[:, :3, :3]))
    return RpeResult(translation=ErrorStats.of(trans), rotation=ErrorStats.of(rot), translation_errors=trans,
                     rotation_errors_deg=rot, pairs=pairs, delta=delta, delta_unit=delta_unit, all_pairs=all_pairs)


def trajectory_rpe(reference: Trajectory, estimate: Trajectory, align: str = "se3", max_diff: float = 0.01,
                   delta: float = 1, delta_unit: str = "frames", all_pairs: bool = False,
                   rel_tol: float = 0.1) -> TrajectoryRpe:
    """RPE of ``estimate`` against ``reference``: the ATE's association and alignment (``se3|sim3|none``), then
    :func:`relative_pose_error` over the matched poses."""
    ref, est, _ = matched_poses(reference, estimate, max_diff)
    ref_pos, est_pos = ref[:, :3, 3], est[:, :3, 3]
    alignment = align_poses(est_pos, ref_pos, align)
    aligned = alignment.apply(est)
    return TrajectoryRpe(relative_pose_error(ref, aligned, delta, delta_unit, all_pairs, rel_tol), alignment, len(ref))
