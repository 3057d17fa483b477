"""Upkeep of the keyframe graph after a keyframe joins: proximity edges to older window keyframes and loop edges
beyond the window, and keyframes turned back into frames (one the BA cannot constrain, one that barely moved).
Functions of the graph, the frames and the parameters; the frontend decides when they run."""
from __future__ import annotations

import logging
from dataclasses import replace

import torch

from services.ba.frontend import edges, steps
from services.ba.frontend.frames import FramePoses, FrameRecord
from services.ba.frontend.graph import KeyframeGraph
from services.ba.frontend.params import GraphParams

logger = logging.getLogger(__name__)


def add_proximity(g: KeyframeGraph, k: int, window: list[int], gp: GraphParams) -> None:
    """Proximity edges from keyframe ``k`` to the window keyframes beyond its temporal radius."""
    cands = [c for c in window if c < k - gp.temporal_radius]
    if not cands:
        return
    state = g.stacked(cands + [k])
    last = len(cands)
    ii = torch.arange(last, device=state.poses.device)
    jj = torch.full_like(ii, last)
    if not (g.predict_flow and gp.proximity_overlap > 0):
        dist = edges.induced_flow(state.poses, state.disparity, g.intrinsics, ii, jj)
    else:
        # a keyframe that turned on the spot has no baseline for its depth; the first keyframe with one to it is
        # linked to it however far it turned (DIS starts from the flow the map predicts, rotation included),
        # judged by the flow its depth causes. Not in a driving turn: there every keyframe has a baseline
        parts = edges.flow_parts(state.poses, state.disparity, g.intrinsics, ii, jj)
        after_turn = k >= 2 and steps.still_between(g, k - 2, k - 1)  # the first keyframe out of a turn
        still = torch.tensor([after_turn or steps.turned_on_the_spot(g, c) for c in cands], device=ii.device)
        turned = still & (parts.rotation >= gp.proximity_max_flow) & (parts.overlap >= gp.proximity_overlap)
        dist = torch.where(turned, parts.parallax, parts.induced)
    chosen = edges.proximity_pairs(k, cands, dist.cpu(), gp)
    g.proximity |= {(g.seqs[a], g.seqs[b]) for a, b in chosen}
    add_loop_edges(g, k, window, gp)


def add_loop_edges(g: KeyframeGraph, k: int, window: list[int], gp: GraphParams) -> None:
    """Proximity edges from keyframe ``k`` to held keyframes older than ``window`` that its view overlaps
    (``gp.loop_overlap`` of their pixels land in it) with little induced flow: a camera back where it was. The window
    BA never sees them; the BA over every held keyframe (``Refinement.refine_globally``, the end of stream) does,
    and pulls the drift since back (the 10,000-frame orbit's scale drifted +27 % over 23 laps without them). At
    most every ``gp.loop_every``-th keyframe: each edge costs a flow and BA work, and two on every keyframe slowed
    the 10,000-frame stream's mapping until tracking, short of CPU, skipped frames (docs/BENCHMARKS.md).
    Landmarks (``KeyframeGraph.landmarks``) get their own edges on the same terms: among the recent keyframes an
    edge goes to the previous lap, whose drift it shares."""
    if gp.loop_max_edges <= 0 or not window or window[0] == 0:
        return
    position = {seq: i for i, seq in enumerate(g.seqs)}  # one pass, not a list search per edge end
    first_recent = max(0, k - gp.loop_every + 1)
    # a loop edge of one of the last loop_every keyframes (one reaching past the window it had) holds the drift
    # as well: per kind of target, so that one to the lap before does not stand for one to a landmark
    looped = {b for a, b in g.proximity if first_recent <= position[a] < k and position[a] - position[b] >= len(window)}
    older = range(window[0])
    for cands in ([c for c in older if g.seqs[c] not in g.landmarks], [c for c in older if g.seqs[c] in g.landmarks]):
        if cands and not looped & {g.seqs[c] for c in cands}:
            _add_loop_edges_to(g, k, cands, gp)


def _flow_parts_into(g: KeyframeGraph, cands: list[int], k: int) -> edges.FlowParts:
    """:func:`edges.flow_parts` of the pairs ``cands`` -> ``k`` (positions)."""
    state = g.stacked(cands + [k])
    ii = torch.arange(len(cands), device=state.poses.device)
    return edges.flow_parts(state.poses, state.disparity, g.intrinsics, ii, torch.full_like(ii, len(cands)))


def _add_loop_edges_to(g: KeyframeGraph, k: int, cands: list[int], gp: GraphParams) -> None:
    parts = _flow_parts_into(g, cands, k)
    dist = torch.where(parts.overlap >= gp.loop_overlap, parts.induced, torch.full_like(parts.induced, float("inf")))
    chosen = edges.proximity_pairs(k, cands, dist.cpu(), replace(gp, proximity_max_edges=gp.loop_max_edges))
    if chosen:
        logger.info("loop edges", extra={"seq": g.seqs[k], "to": sorted({g.seqs[b] for a, b in chosen if a == k})})
    g.proximity |= {(g.seqs[a], g.seqs[b]) for a, b in chosen}


def new_place(g: KeyframeGraph, k: int, gp: GraphParams) -> bool:
    """Whether keyframe ``k`` (about to leave the held keyframes) shows a place no landmark shows: no landmark has
    ``gp.landmark_overlap`` of its pixels land in ``k`` with an induced flow below ``gp.proximity_max_flow``."""
    landmarks = g.landmark_positions()
    if not landmarks:
        return True
    parts = _flow_parts_into(g, landmarks, k)
    seen = (parts.overlap >= gp.landmark_overlap) & (parts.induced < gp.proximity_max_flow)
    return not bool(seen.any())


def unconstrained(g: KeyframeGraph, window: list[int]) -> int | None:
    """The keyframe whose step made the last BA result refused, when it is interior to ``window``: its flow does
    not constrain its pose (under rotation its baseline is tiny), and while it stays every later BA is refused the
    same way (hand-held yaw: 22 of 27). The newest waits until a later keyframe makes it interior."""
    seq = g.jumped_seq
    if seq is None or seq not in g.seqs or g.index(seq) in (window[0], len(g) - 1):
        return None
    return g.index(seq)


def redundant(g: KeyframeGraph, gp: GraphParams) -> int | None:
    """The second-newest keyframe when it barely moved from the one before (mean induced flow below
    ``remove_max_flow``), else None; the caller turns it into a frame."""
    if len(g) < 4:
        return None
    k = len(g) - 2
    state = g.stacked([k - 1, k])
    dist = edges.induced_flow(state.poses, state.disparity, g.intrinsics, torch.tensor([0, 1]), torch.tensor([1, 0]))
    if float(dist.mean()) >= gp.remove_max_flow:
        return None
    logger.info("redundant keyframe turned into a frame", extra={"seq": g.seqs[k], "flow": float(dist.mean())})
    return k


def to_frame(g: KeyframeGraph, frames: FramePoses, k: int) -> int:
    """Keyframe ``k`` leaves the graph and becomes a frame again; returns its seq."""
    seq = g.seqs[k]
    frames.add(FrameRecord(seq, g.stamps[k], g.images[k]))
    g.remove(k)
    frames.forget_targets(seq)
    return seq
