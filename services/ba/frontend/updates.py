"""What the frontend hands out: the graph's state and poses as numpy, copied off the BA device (no transport)."""
from __future__ import annotations

import logging
from typing import NamedTuple

import numpy as np
import torch

from services.ba.frontend.frames import FramePoses
from services.ba.frontend.graph import KeyframeGraph, working_intrinsics
from services.common.rotations import is_rigid

log = logging.getLogger(__name__)


class GraphUpdate(NamedTuple):
    kf_seqs: np.ndarray  # (N,) int64 every keyframe held, landmarks aside
    poses: np.ndarray  # (N, 4, 4) float64 world_from_cam
    intrinsics: np.ndarray  # (4,) float64 at working resolution
    updated_seqs: np.ndarray  # (M,) int64 keyframes whose maps below changed
    disparities: np.ndarray  # (M, h, w) float32
    static_weights: np.ndarray  # (M, h, w) float32 ARK weight (1 static, 0 dynamic)
    confidence: np.ndarray  # (M, h, w) float32 mean flow confidence
    metric: bool  # a depth prior fixed the scale


class PoseUpdate(NamedTuple):
    frame_seqs: np.ndarray  # (F,) int64
    stamps_ns: np.ndarray  # (F,) int64
    poses: np.ndarray  # (F, 4, 4) float64 world_from_cam


class Update(NamedTuple):
    graph: GraphUpdate | None = None
    poses: PoseUpdate | None = None
    intrinsics_changed: bool = False


def graph_update(g: KeyframeGraph, updated: list[int], metric: bool) -> GraphUpdate:
    """Every held keyframe's pose, and the maps of the keyframes at positions ``updated``. Landmarks are left out, as
    keyframes that left the graph are: their poses are final (the BA holds them fixed), and the mapstore folds
    them in order with the others."""
    recent = g.recent()
    updated = [k for k in updated if g.seqs[k] not in g.landmarks]
    return GraphUpdate(
        kf_seqs=np.array([g.seqs[k] for k in recent], np.int64), poses=to_numpy([g.poses[k] for k in recent],
                                                                                np.float64),
        intrinsics=working_intrinsics(g.intrinsics), updated_seqs=np.array([g.seqs[k] for k in updated], np.int64),
        disparities=to_numpy([g.disparity[k] for k in updated], np.float32),
        static_weights=to_numpy([g.static[k] for k in updated], np.float32),
        confidence=to_numpy([g.confidence[k] for k in updated], np.float32), metric=metric)


def pose_update(g: KeyframeGraph, frames: FramePoses, frame_seqs: list[int]) -> PoseUpdate | None:
    """The poses of ``frame_seqs`` (keyframes from the graph, frames from their anchors) in seq order, those that
    are rigid transforms only (a pose that is not has no quaternion, and no consumer can use it); None when there
    is none."""
    seqs, stamps, poses = [], [], []
    for seq in frame_seqs:
        if seq in g.seqs:
            k = g.index(seq)
            pose, stamp = g.poses[k], g.stamps[k]
        else:
            pose, stamp = frames.pose(g, seq), frames.frames[seq].stamp
        if pose is not None and bool(torch.isfinite(pose).all()):
            seqs.append(seq), stamps.append(stamp), poses.append(pose)
    if not seqs:
        return None
    order = np.argsort(seqs)
    arrays = to_numpy(poses, np.float64)[order]
    rigid = is_rigid(arrays)
    if not rigid.all():
        log.warning("poses that are not rigid transforms left out", extra={
            "seqs": np.array(seqs, np.int64)[order][~rigid].tolist()})
        if not rigid.any():
            return None
    return PoseUpdate(np.array(seqs, np.int64)[order][rigid], np.array(stamps, np.int64)[order][rigid], arrays[rigid])


def to_numpy(tensors: list[torch.Tensor], dtype) -> np.ndarray:
    """``tensors`` stacked into one host array of ``dtype``, wherever they live."""
    return torch.stack(tensors).detach().cpu().numpy().astype(dtype)
