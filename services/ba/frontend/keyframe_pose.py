"""A new keyframe's pose before its window BA: motion-only alignment to the keyframe before it, relocalised from
PnP where its flow barely supports it, and kept within the plausible speed.

When mapping is behind a live camera the keyframe before may be a deferred one: its depth was carried over from
the newest keyframe a BA refined, and its cells where no point landed hold the median disparity, not a point.
Aligned to those cells, a chain of deferred keyframes drifted in scale (KITTI live, mapping 4 keyframes behind:
+23 % over frames 20-50 as the car speeds up). So only its measured cells count, and the pose is aligned again
jointly with that refined keyframe. ``carried`` maps a deferred keyframe's seq to its (h, w) 0/1 measured mask.
"""
from __future__ import annotations

import logging

import numpy as np
import torch

from services.ba.frontend import motion, relocalise, steps
from services.ba.frontend.graph import KeyframeGraph
from services.ba.frontend.params import FrontendParams

logger = logging.getLogger(__name__)


def align_keyframe(g: KeyframeGraph, k: int, carried: dict[int, np.ndarray],
                   params: FrontendParams) -> tuple[float, bool]:
    """Sets keyframe ``k``'s pose in ``g``. Returns the share of the grid (of its measured cells, after a deferred
    keyframe) that supports it (the alignment's robust weight; 0 where the step was implausible and the bounded
    prediction taken), and whether the pose came from a PnP start (``relocalise.realign_keyframe``)."""
    device = g.poses[k].device
    t = g.targets(k - 1, k)
    known = measured(g, carried, k - 1)
    confidence = relocalise.masked(t.confidence.to(device), known)
    res = motion.align(g.poses[k], g.poses[k - 1][None], g.disparity[k - 1][None], t.target[None].to(device),
                       confidence[None], g.intrinsics, params.motion)
    aligned, res = res, relocalise.realign_keyframe(g, k, res, params.motion, params.relocalise, known)
    pose = torch.from_numpy(res.pose).to(g.poses[k]) if res.ok else g.poses[k]
    if res.ok and known is not None:
        pose = _align_to_refined(g, k, pose, carried, known, params)
    if not steps.plausible(g, pose, k, params.max_step_growth):
        logger.info("keyframe pose implausible; bounded constant-velocity prediction kept", extra={"seq": g.seqs[k]})
        g.poses[k] = steps.bounded_prediction(g, k)
        return 0.0, res is not aligned
    g.poses[k] = pose
    return (res.weight / relocalise.cells(g, k, known) if res.ok else 0.0), res is not aligned


def _align_to_refined(g: KeyframeGraph, k: int, pose: torch.Tensor, carried: dict[int, np.ndarray],
                      known: torch.Tensor, params: FrontendParams) -> torch.Tensor:
    """``pose`` of keyframe ``k`` (aligned to the deferred keyframe before it, whose measured cells are ``known``)
    aligned again to those cells and to the newest keyframe a BA refined, together: the carried-over depth alone is
    a visual odometry's. One more flow per deferred keyframe (at the live flow size); ``pose`` unchanged if there
    is no refined keyframe or the alignment fails."""
    refined = newest_refined(g, carried, k - 1)
    if refined is None:
        return pose
    pair = [k - 1, refined]
    flows = [g.targets(i, k) for i in pair]
    device = pose.device
    confidence = torch.stack([relocalise.masked(flows[0].confidence.to(device), known), flows[1].confidence.to(device)])
    targets = torch.stack([f.target.to(device) for f in flows])
    res = motion.align(pose, torch.stack([g.poses[i] for i in pair]), torch.stack([g.disparity[i] for i in pair]),
                       targets, confidence, g.intrinsics, params.motion)
    return torch.from_numpy(res.pose).to(pose) if res.ok and bool(np.isfinite(res.pose).all()) else pose


def newest_refined(g: KeyframeGraph, carried: dict[int, np.ndarray], k: int) -> int | None:
    """The newest keyframe before ``k`` whose depth a BA refined (not a deferred one's carried depth); None when
    there is none."""
    return next((i for i in range(k - 1, -1, -1) if g.seqs[i] not in carried), None)


def measured(g: KeyframeGraph, carried: dict[int, np.ndarray], k: int) -> torch.Tensor | None:
    """(h, w) 1 where keyframe ``k``'s depth holds a point, 0 where it was filled in; None: all of it (a BA refined
    it)."""
    known = carried.get(g.seqs[k])
    return None if known is None else torch.from_numpy(np.asarray(known, np.float32)).to(g.disparity[k].device)
