"""How ba's mapping loop meets restarts: its own (a checkpoint resumed, what features sends again recognised as
held) and the mapstore's (a restarted mapstore is sent the last stream's end again), and when features' end of
stream may be handled (Zenoh orders messages per key, not across keys)."""
from __future__ import annotations

import logging
import threading
from typing import TYPE_CHECKING

from services.ba.checkpoint import Checkpointer
from services.ba.settings import BaSettings
from services.common.bus import Delivery
from services.common.restarts import Restarts
from services.common.schema import Credit, Eos, FrameLite, Keyframe

if TYPE_CHECKING:
    from services.ba.service import BaState

log = logging.getLogger(__name__)


def seen_before(state: BaState, msg: Keyframe | FrameLite, resumed_at: int) -> bool:
    """A frame or keyframe this stream's state already holds: covered by the checkpoint it resumed from, of a
    stream that ended, or a keyframe no newer than the graph's newest (features sends keyframes in order)."""
    if msg.seq <= resumed_at or msg.seq <= state.ended_upto:
        return True
    graph = state.frontend.graph
    return isinstance(msg, Keyframe) and graph is not None and bool(graph.seqs) and msg.seq <= graph.seqs[-1]


def watch_mapstores(bus, key: str) -> threading.Event:
    """Set whenever a mapstore consumer appears after another one did (a mapstore that restarted)."""
    mapstores, restarted = Restarts("mapstore-"), threading.Event()

    def on_progress(delivery: Delivery) -> None:
        if mapstores.replaced_by(delivery.msg.consumer):
            restarted.set()

    bus.subscribe(key, on_progress, [Credit])
    return restarted


def resume(state: BaState, checkpoints: Checkpointer, cfg: BaSettings) -> int:
    """Put the stream's checkpoint, if there is one, into ``state``; the seq it holds (-1: none)."""
    ckpt = checkpoints.load(state.frontend.device)
    if ckpt is None:
        return -1
    for name, value in ckpt.fields.items():
        setattr(state, name, value)
    log.info("resumed from checkpoint", extra={"stream": cfg.stream, "seq": ckpt.seq, "keyframes": state.keyframes})
    return ckpt.seq


def stream_complete(state: BaState, eos: Eos, queued: int) -> bool:
    """Zenoh keeps order per key, not across keys: the EOS can overtake the last keyframes. It is handled once
    every keyframe features announced (its ``count``) has arrived and nothing else is queued."""
    return state.keyframes_seen >= eos.count and queued == 0
