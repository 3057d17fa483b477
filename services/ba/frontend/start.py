"""Starting the map, and the one focal calibration after it: what the frontend decides before its map exists.

Keyframes are collected until the first and the newest have parallax; then a two-view start (:mod:`init`) seeds
every keyframe, or, when their flow is explained by a rotation alone (a camera turning on the spot), a map of
rotations starts. A start that fails with parallax slides its window forward; a camera that has not moved for
long gets a static map rather than holding every frame. Functions of the graph and the frames: the frontend keeps
the state of whether its map has started.
"""
from __future__ import annotations

import dataclasses
import logging

from services.ba.core.params import BAParams
from services.ba.frontend import init
from services.ba.frontend.frames import FramePoses, FrameRecord
from services.ba.frontend.graph import KeyframeGraph
from services.ba.frontend.params import FrontendParams, InitParams, focal_ba

logger = logging.getLogger(__name__)

TURNING, TWO_VIEW = "turning", "two_view"


def try_start(graph: KeyframeGraph, frames: FramePoses, params: FrontendParams, ba: BAParams,
              force: bool = False) -> str | None:
    """Start the map from the keyframes held: :data:`TURNING` (a map of rotations; depth comes with the first
    translation), :data:`TWO_VIEW`, or None while it waits (the window slid on where a start with parallax
    failed). ``force``: start with what there is."""
    if not force and init.turning(graph, params.init):
        init.start_static(graph)
        return TURNING
    cost = init.start_map(graph, params.init, ba, params.motion, force)
    if cost is None:
        slide_window(graph, frames, params.init)
        return None
    if cost == float("inf"):
        logger.warning("two-view start failed at end of stream; keyframes keep identity poses")
    return TWO_VIEW


def calibrate_focal(graph: KeyframeGraph, frames: FramePoses, params: FrontendParams, live: bool) -> None:
    """Once, at ``focal_after`` keyframes: the multi-start focal calibration (:func:`init.calibrate_focal`); when a
    restart won, the map has a new scale and focal and every frame is aligned again."""
    ba = focal_ba(dataclasses.replace(params.ba, iterations=params.init.iterations), params)
    restarts = params.live_focal_restarts if live else params.focal_restarts
    only_undetermined = live and params.live_calibration == "when_undetermined"
    if init.calibrate_focal(graph, params.init, ba, params.motion, restarts, only_undetermined) is not None \
            and not live:
        # the restarted map is in the scale of the old one (init._keep_scale), so a live stream's frames keep
        # their anchors: their poses went out when tracked, and aligning them all again would stall mapping
        frames.unanchor()


def slide_window(graph: KeyframeGraph, frames: FramePoses, params: InitParams) -> None:
    """A two-view start that fails although the first and newest keyframe have parallax will not succeed with a
    still longer baseline (fast motion: the flow between them breaks). Past ``max_keyframes``, the oldest keyframe
    is turned back into a frame, so the next attempt uses a closer pair."""
    if len(graph) <= params.max_keyframes or not has_parallax(graph, params):
        return  # no parallax yet: waiting is right, the keyframes stay
    seq = graph.seqs[0]
    logger.info("two-view start failed with parallax; oldest keyframe turned into a frame", extra={"seq": seq})
    frames.add(FrameRecord(seq, graph.stamps[0], graph.images[0]))
    graph.remove(0)


def static_for_long(graph: KeyframeGraph | None, frames: FramePoses, params: InitParams) -> bool:
    """More than ``max_pending_frames`` frames wait for a map and the keyframes have no parallax: a fixed camera.
    Waiting for the end of stream would hold every frame (memory) and leave them all without a pose."""
    return (graph is not None and len(frames.frames) > params.max_pending_frames
            and (len(graph) < 2 or not has_parallax(graph, params)))


def has_parallax(graph: KeyframeGraph, params: InitParams) -> bool:
    """The first and newest keyframe have flow enough for a two-view start."""
    return init.parallax(graph) >= params.min_flow
