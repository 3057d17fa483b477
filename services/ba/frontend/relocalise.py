"""Relocalisation of a keyframe: its motion-only alignment started again from a PnP pose against the keyframe
before it (:mod:`services.ba.frontend.pnp`, which says why), kept when the flow supports it more."""
from __future__ import annotations

import logging

import numpy as np
import torch

from services.ba.frontend import motion
from services.ba.frontend.graph import KeyframeGraph
from services.ba.frontend.motion import MotionResult
from services.ba.frontend.params import MotionParams, RelocaliseParams
from services.ba.frontend.pnp import pnp_pose

logger = logging.getLogger(__name__)


def realign_keyframe(graph: KeyframeGraph, k: int, aligned: MotionResult, motion_params: MotionParams,
                     params: RelocaliseParams, known: torch.Tensor | None = None) -> MotionResult:
    """Keyframe ``k``'s motion-only alignment to keyframe ``k - 1``, ``aligned`` (started from the motion
    prediction), against the same alignment started from the PnP pose, with the flow between the two computed
    afresh from the flow that pose induces. Runs only when ``aligned`` keeps less than ``params.below_share`` of
    the grid (of its cells that hold a point: ``known``, (h, w) 0/1, where ``k - 1``'s depth was carried over).
    Returns the result the flow supports more (the larger robust weight); the graph's cached flows and pose of
    ``k`` are left as that start made them."""
    n_cells = cells(graph, k, known)
    if aligned.ok and aligned.weight >= params.below_share * n_cells:
        return aligned
    found = pnp_pose(graph.images[k - 1], graph.poses[k - 1], graph.disparity[k - 1], graph.intrinsics,
                     graph.images[k], params)
    if found is None:
        logger.info("keyframe barely supported and not relocalised (too few ORB matches agree)",
                    extra={"seq": graph.seqs[k], "share": round(aligned.weight / n_cells, 3)})
        return aligned
    guess, before = graph.poses[k], graph.take_flows(k - 1, k)
    graph.poses[k] = torch.from_numpy(found.pose).to(guess)
    t = graph.targets(k - 1, k)
    dev = graph.device
    confidence = masked(t.confidence.to(dev), known)
    res = motion.align(found.pose, graph.poses[k - 1][None], graph.disparity[k - 1][None], t.target[None].to(dev),
                       confidence[None], graph.intrinsics, motion_params)
    better = res.ok and bool(np.isfinite(res.pose).all()) and (not aligned.ok or res.weight > aligned.weight)
    logger.info("keyframe relocalised" if better else "keyframe's relocalised start less supported; kept",
                extra={"seq": graph.seqs[k], "inliers": found.inliers,
                       "share_before": round(aligned.weight / n_cells, 3), "share_after": round(res.weight / n_cells, 3)})
    if better:
        return res
    graph.take_flows(k - 1, k)
    graph.put_flows(before)
    graph.poses[k] = guess
    return aligned


def masked(confidence: torch.Tensor, known: torch.Tensor | None) -> torch.Tensor:
    """Flow ``confidence`` of keyframe ``k - 1``'s cells, 0 where its carried-over depth was filled in (``known``:
    (h, w) 0/1; None: every cell holds a point)."""
    return confidence if known is None else confidence * known.to(confidence)


def cells(graph: KeyframeGraph, k: int, known: torch.Tensor | None) -> float:
    """How many of keyframe ``k - 1``'s grid cells hold a point: the denominator of a support share."""
    return float(graph.disparity[k - 1].numel()) if known is None else max(float(known.sum()), 1.0)
