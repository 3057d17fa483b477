"""Semantic map quality against exact ground truth (the synthetic world): pure arrays in, named results out.

The estimated map has no metric scale, so its points are first brought into the ground-truth world frame with
the Sim(3) that aligns the estimated trajectory to the true one (:func:`services.evaluation.ate.umeyama`).
Each map point then takes the label of its nearest ground-truth point, if one lies within ``max_dist``
(metres); unmatched points count as geometric outliers and take no part in the label scores.

- per label L: precision = |pred L ∧ GT L| / |pred L|, recall = |pred L ∧ GT L| / |GT L|, IoU = TP/(TP+FP+FN),
  over the matched map points (pred = the map's argmax label);
- mIoU over the labels that occur among the matched points' GT labels;
- box overlap: IoU of a returned region's box (an oriented box once carried into the GT frame by the
  Sim(3)) with the true object's box;
- moving objects: the fraction of their GT points that have a map point within ``max_dist`` *explained by
  them* (whose nearest GT point is a moving one, so the floor under a walking person does not count);
  split by :func:`inside_any_box` into the places the objects have left (should be absent: later views see
  them empty) and where they are at the end (the current truth).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from scipy.spatial import cKDTree

from .ate import Alignment


class GtPoints(NamedTuple):
    """Ground-truth surface samples in the world frame (N points)."""

    xyz: np.ndarray  # (N, 3) float64 metres, world frame
    label: np.ndarray  # (N,) int32 label index
    dynamic: np.ndarray  # (N,) bool: the point lies on an object that moves at some time in the sequence


class LabelScores(NamedTuple):
    """Per-label point classification scores (L labels); NaN where a ratio has no denominator."""

    precision: np.ndarray  # (L,) float64
    recall: np.ndarray  # (L,) float64
    iou: np.ndarray  # (L,) float64
    support: np.ndarray  # (L,) int64 matched map points whose GT label is L
    predicted: np.ndarray  # (L,) int64 matched map points predicted as L
    miou: float  # mean IoU over labels with support > 0


class Matching(NamedTuple):
    """Nearest ground-truth point of each map point (M points)."""

    index: np.ndarray  # (M,) int64 index into the GT points (valid only where ``matched``)
    distance: np.ndarray  # (M,) float64 metres
    matched: np.ndarray  # (M,) bool: distance <= max_dist


@dataclass(frozen=True)
class MapQualityParams:
    """Tolerances of the evaluation."""

    max_dist: float = 0.10
    """Metres: a map point and a GT point within this distance are the same surface."""
    gt_stride: int = 4
    """Pixels between GT depth samples (both axes) when GT points are made from depth maps."""


def backproject_frame(depth: np.ndarray, world_from_cam: np.ndarray, intrinsics: np.ndarray, stride: int) -> np.ndarray:
    """World points of every ``stride``-th pixel (rows and columns from 0) of an (H, W) float depth map (metres,
    camera z). ``world_from_cam`` (4, 4), ``intrinsics`` (fx, fy, cx, cy) pixels. Returns (H/s·W/s, 3) float64."""
    if depth.ndim != 2 or np.shape(world_from_cam) != (4, 4) or np.shape(intrinsics) != (4,):
        raise ValueError(f"depth (H, W), pose (4, 4), intrinsics (4,) expected; got {depth.shape}, "
                         f"{np.shape(world_from_cam)}, {np.shape(intrinsics)}")
    fx, fy, cx, cy = np.asarray(intrinsics, np.float64)
    v, u = np.mgrid[0:depth.shape[0]:stride, 0:depth.shape[1]:stride].astype(np.float64)
    z = depth[::stride, ::stride].astype(np.float64)
    cam = np.stack([(u - cx) / fx * z, (v - cy) / fy * z, z], -1).reshape(-1, 3)
    return cam @ np.asarray(world_from_cam)[:3, :3].T + np.asarray(world_from_cam)[:3, 3]


def gt_points_of_frame(depth: np.ndarray, labels: np.ndarray, dynamic: np.ndarray, world_from_cam: np.ndarray,
                       intrinsics: np.ndarray, stride: int) -> GtPoints:
    """GT points of one frame: (H, W) depth (m), labels (int), dynamic (bool) maps, sampled every ``stride`` px."""
    if labels.shape != depth.shape or dynamic.shape != depth.shape:
        raise ValueError(f"labels {labels.shape} and dynamic {dynamic.shape} must match depth {depth.shape}")
    xyz = backproject_frame(depth, world_from_cam, intrinsics, stride)
    return GtPoints(xyz, labels[::stride, ::stride].reshape(-1).astype(np.int32),
                    dynamic[::stride, ::stride].reshape(-1).astype(bool))


def concat_gt(parts: list[GtPoints]) -> GtPoints:
    """One :class:`GtPoints` of several frames'."""
    return GtPoints(*(np.concatenate([getattr(p, f) for p in parts]) for f in GtPoints._fields))


def apply_sim3(alignment: Alignment, xyz: np.ndarray) -> np.ndarray:
    """(N, 3) points of the estimated frame → GT frame: s·R·x + t."""
    return alignment.scale * np.asarray(xyz, np.float64) @ alignment.rotation.T + alignment.translation


def match_to_gt(map_xyz: np.ndarray, gt: GtPoints, max_dist: float) -> Matching:
    """Nearest GT point of each (M, 3) map point (GT frame, metres)."""
    if len(gt.xyz) == 0:
        raise ValueError("no ground-truth points to match against")
    dist, idx = cKDTree(gt.xyz).query(np.asarray(map_xyz, np.float64), k=1)
    return Matching(np.asarray(idx, np.int64), np.asarray(dist), np.asarray(dist) <= max_dist)


AMBIGUOUS = -2
"""Label of a map point whose ``max_dist`` neighbourhood holds GT points of more than one label."""
MOVING = -3
"""Label of a map point within ``max_dist`` of a moving object's GT point (``unambiguous_labels(moving=False)``)."""


def unambiguous_labels(map_xyz: np.ndarray, gt: GtPoints, max_dist: float, moving: bool = True) -> np.ndarray:
    """(M,) GT label of each map point: the one label of every GT point within ``max_dist``; -1 when none lies
    that close, ``AMBIGUOUS`` when they disagree. A voxel there fuses the features of two surfaces (a chair leg
    and the floor round it), so it has no single true label and its nearest GT point's is a coin toss.
    ``moving=False``: a point near any GT point of an object that moves during the sequence is ``MOVING``: the map
    leaves such objects out, so where they were (and are) says nothing of the static map's labels."""
    xyz = np.asarray(map_xyz, np.float64)
    near = cKDTree(gt.xyz).query_ball_point(xyz, max_dist)
    out = np.full(len(near), -1, np.int64)
    for i, idx in enumerate(near):
        if idx:
            labels = gt.label[idx]
            out[i] = labels[0] if (labels == labels[0]).all() else AMBIGUOUS
    if not moving and gt.dynamic.any() and len(xyz):
        dist, _ = cKDTree(gt.xyz[gt.dynamic]).query(xyz)
        out[dist <= max_dist] = MOVING
    return out


def label_scores(predicted: np.ndarray, truth: np.ndarray, n_labels: int) -> LabelScores:
    """Per-label precision / recall / IoU of (M,) predicted against (M,) true labels (both in [0, n_labels))."""
    if predicted.shape != truth.shape or predicted.ndim != 1:
        raise ValueError(f"predicted and truth must be matching (M,), got {predicted.shape}, {truth.shape}")
    confusion = np.zeros((n_labels, n_labels), np.int64)  # rows: truth, columns: predicted
    np.add.at(confusion, (truth.astype(np.int64), predicted.astype(np.int64)), 1)
    tp = np.diag(confusion).astype(np.float64)
    support, pred = confusion.sum(1), confusion.sum(0)
    with np.errstate(invalid="ignore", divide="ignore"):
        precision, recall = tp / pred, tp / support
        iou = tp / (support + pred - tp)
    present = support > 0
    miou = float(np.nanmean(np.where(present, np.nan_to_num(iou), np.nan))) if present.any() else float("nan")
    return LabelScores(precision, recall, iou, support, pred, miou)


def box_iou(a_min: np.ndarray, a_max: np.ndarray, b_min: np.ndarray, b_max: np.ndarray) -> float:
    """IoU of two axis-aligned boxes given by (3,) corners."""
    inter = np.prod(np.clip(np.minimum(a_max, b_max) - np.maximum(a_min, b_min), 0, None))
    union = np.prod(np.subtract(a_max, a_min)) + np.prod(np.subtract(b_max, b_min)) - inter
    return float(inter / union) if union > 0 else 0.0


def aligned_box_iou(alignment: Alignment, box_min: np.ndarray, box_max: np.ndarray, gt_min: np.ndarray,
                    gt_max: np.ndarray, samples_per_side: int = 24) -> float:
    """IoU of an estimated-frame axis-aligned box, carried into the GT frame by the Sim(3) (where it is an oriented
    box), with a GT axis-aligned box. The intersection is measured on a regular grid of
    ``samples_per_side``³ cell centres of the estimated box (error ≲ 3/samples_per_side of its volume)."""
    box_min, box_max = np.asarray(box_min, np.float64), np.asarray(box_max, np.float64)
    extent = box_max - box_min
    if np.any(extent < 0):
        raise ValueError(f"box_min {box_min} must not exceed box_max {box_max}")
    t = (np.arange(samples_per_side) + 0.5) / samples_per_side
    grid = np.stack(np.meshgrid(t, t, t, indexing="ij"), -1).reshape(-1, 3) * extent + box_min
    moved = apply_sim3(alignment, grid)
    inside = np.all((moved >= gt_min) & (moved <= gt_max), axis=1).mean()
    vol_est = float(np.prod(extent)) * alignment.scale**3
    inter = inside * vol_est
    union = vol_est + float(np.prod(np.subtract(gt_max, gt_min))) - inter
    return float(inter / union) if union > 0 else 0.0


def moving_presence(gt: GtPoints, matching: Matching, map_xyz: np.ndarray, max_dist: float,
                    only: np.ndarray | None = None) -> float:
    """Fraction of the moving objects' GT points with a map point within ``max_dist`` that the moving object
    explains (its nearest GT point is a moving one). ``only``: (N,) bool mask restricting which moving GT points
    count (e.g. one object's label). NaN when no GT point qualifies."""
    moving_mask = gt.dynamic if only is None else gt.dynamic & only
    moving = np.flatnonzero(moving_mask)
    if len(moving) == 0:
        return float("nan")
    explained = matching.matched & moving_mask[matching.index]
    if not explained.any():
        return 0.0
    tree = cKDTree(np.asarray(map_xyz, np.float64)[explained])
    dist, _ = tree.query(gt.xyz[moving], k=1)
    return float(np.mean(dist <= max_dist))


def inside_any_box(xyz: np.ndarray, lo: np.ndarray, hi: np.ndarray, margin: float = 0.0) -> np.ndarray:
    """(N,) bool: each of the (N, 3) points lies in at least one of the (B, 3)–(B, 3) axis-aligned boxes grown by
    ``margin`` (metres) on every side (surface samples lie on the faces, so a small margin keeps them in)."""
    xyz, lo, hi = np.asarray(xyz, np.float64), np.atleast_2d(lo), np.atleast_2d(hi)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or lo.shape != hi.shape or lo.shape[1:] != (3,):
        raise ValueError(f"points (N, 3) and boxes (B, 3) expected, got {xyz.shape}, {lo.shape}, {hi.shape}")
    inside = (xyz[:, None, :] >= lo[None] - margin) & (xyz[:, None, :] <= hi[None] + margin)
    return inside.all(axis=2).any(axis=1)
