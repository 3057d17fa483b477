"""ba's mapping in its spare time: frames tracking posed solved again with mapping's own flow, and the background
BA over the held keyframes; what they revise goes out as outputs (``Frontend.refine_frame``,
``Frontend.refine_globally``)."""
from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING

from services.ba.outputs import Outputs, outputs_at, poses_out
from services.common.bus import Inbox

if TYPE_CHECKING:
    from services.ba.service import BaState
    from services.ba.settings import BaSettings

log = logging.getLogger(__name__)


def refine_while_idle(state: BaState, inboxes: tuple[Inbox, ...], cfg: BaSettings) -> Outputs:
    """Mapping has nothing queued: the background BA over the held keyframes when one is due; else a live stream's
    frames that tracking posed are aligned again with mapping's own flow (``Frontend.refine_frame``), a few at a
    time, until a message comes to one of ``inboxes`` (mapping's, and tracking's when tracking runs on a thread of
    this interpreter: its frame must not wait behind a refinement). What they revise goes out. The BA comes first:
    a live stream always has a tracked frame to align again, and the BA would never run behind them."""
    if any(box.qsize() for box in inboxes):
        return []
    out = refine_globally(state)
    if out:
        return out
    for _ in range(cfg.refine_frames_per_idle):
        if any(box.qsize() for box in inboxes):
            break
        try:
            update = state.frontend.refine_frame()
        except (ValueError, RuntimeError) as exc:  # a refinement is optional: the tracked pose stands
            log.warning("frame refinement failed", extra={"stream": state.stream, "error": str(exc)})
            break
        if update.poses is None:
            break
        log.debug("frame refined", extra={"stream": state.stream, "seq": int(update.poses.frame_seqs[-1])})
        out.append(poses_out(state.stream, int(update.poses.frame_seqs[-1]), time.time_ns(), update.poses, False))
    return out


def refine_globally(state: BaState) -> Outputs:
    """The BA over every held keyframe, when one is due (``Frontend.refine_globally``): in mapping's spare time,
    and on a lossless stream also after a keyframe while more wait (``background_ba_when_busy``); its graph and
    poses go out as revisions."""
    try:
        update = state.frontend.refine_globally()
    except (ValueError, RuntimeError) as exc:  # optional work: the window's state stands
        log.warning("background global BA failed", extra={"stream": state.stream, "error": str(exc)})
        return []
    if update.graph is None:
        return []
    return outputs_at(state.frontend, state.stream, int(update.graph.kf_seqs[-1]), time.time_ns(), update, final=False)
