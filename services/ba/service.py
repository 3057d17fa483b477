"""BA service: ``keyframe`` / ``frame_lite`` / ``codes`` / ``pca`` / ``eos`` in; ``graph``, ``pose``,
``intrinsics``, ``progress`` and ``eos`` out. One handler per message kind; ``run`` only receives, handles and
publishes.

Tracking and mapping apart, as PTAM and DSO split them: tracking (services/ba/tracking.py, its tracker in a
child process) poses every frame on arrival against the newest mapped keyframe and publishes it at once
(``tracked=True``); mapping (this loop) runs the
window BA per keyframe, revises poses, and hands tracking a new reference after each BA. Keyframes arrive
without codes; their ``codes`` follow when features' backbone is done (the fixed kernel runs until then, ARK
after). In real time, when keyframes queue up behind mapping the oldest is merged as a frame. Progress reports
(highest frame seq mapping has handled) let features hold a lossless stream back while mapping is behind.

At the features stage's end of stream the frontend runs its BA over the keyframes it still holds and the final
``graph`` and ``pose`` (``final=True``) go out before this stage's own ``eos``.

PCA versions: BA compares codes of different keyframes (ARK's cosine similarity, the embedding residual), so
every code in the graph is in one version, ``BaState.pca_version`` — the newest basis seen (or, before any, the
version of the first keyframe's codes). Keyframes are converted on arrival; a newer basis converts the whole
graph from the codes each keyframe arrived with (services/common/pca_codes.py). Codes whose basis is unknown
are left out (None) with a warning: windows holding such a keyframe run without codes until the basis comes.
A version no ``pca`` message brought (missed while down, or lost) is asked of features' ``pca`` queryable
(`BasisFetch`: once, then again every ``retry_s`` while it fails); the reply goes through `handle_pca`.
"""
from __future__ import annotations

import logging
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch

from services.common import keys
from services.common.bus import Bus
from services.common.pca_codes import code_map, convert_codes
from services.common.pca_fetch import BasisFetch
from services.common.bus import Delivery, Inbox
from services.common.lifecycle import MemoryRelease, nice_this_thread
from services.common.own_pages import own_pages
from services.common.restarts import consumer_name
from services.common.streams import hold, session_of
from services.common.schema import Credit, Eos, FrameLite, Keyframe, KeyframeCodes, Message, PcaBasis
from services.ba import recovery
from services.ba.outputs import Outputs, outputs_of, poses_out
from services.ba.spare_time import refine_globally, refine_while_idle
from services.ba.checkpoint import Checkpointer
from services.ba.frontend.frontend import FrameInput, Frontend, KeyframeInput
from services.ba.frontend.graph import NativeCodes
from services.ba.settings import BaSettings
from services.ba.tracking import Anchor, TrackingLoop

log = logging.getLogger(__name__)
POLL_S = 0.05
PROGRESS_PERIOD_S = 0.1



@dataclass
class BaState:
    frontend: Frontend
    stream: str
    pca_version: int = -1  # the version every code in the graph is in (-1: none yet)
    bases: dict[int, PcaBasis] = field(default_factory=dict)  # every basis seen, by version (kept across streams)
    last_seq: int = -1  # highest frame seq seen (keyframe or lite)
    keyframes: int = 0  # keyframes taken into the graph in this stream
    keyframes_seen: int = 0  # keyframe messages received in this stream (taken or refused)
    rejected: Counter = field(default_factory=Counter)  # reason -> messages refused (logged, never fatal)
    pca_fetch: BasisFetch = field(default_factory=BasisFetch)  # versions asked of features' pca queryable
    early_codes: dict[int, KeyframeCodes] = field(default_factory=dict)  # codes that came before their keyframe
    keyframe_backlog: int = 0  # keyframes waiting in the inbox (set by the loop; real-time merging)
    merged: int = 0  # real-time keyframes merged as frames because mapping was behind
    merged_in_a_row: int = 0
    dropped: int = 0  # frames the inboxes dropped by the real-time policy (set at end of stream)
    # frame seq -> where tracking put it, from the tracking thread, which fills it (a checkpoint of an earlier
    # version holds plain (ref_seq, ref_from_cam, world_from_cam) tuples: _take_anchor reads both)
    anchors: dict[int, Anchor] = field(default_factory=dict)
    ended_upto: int = -1  # the last frame seq of a stream that ended: anything up to it comes again, not anew
    final_outputs: Outputs = field(default_factory=list)  # the last stream's final graph, poses and EOS


def build_state(cfg: BaSettings) -> BaState:
    torch.set_num_threads(cfg.threads)
    return BaState(Frontend(cfg.frontend_params(), cfg.torch_device()), cfg.stream)


def handle_keyframe(state: BaState, msg: Keyframe, cfg: BaSettings) -> Outputs:
    if _merge(state, msg, cfg):
        state.merged += 1  # mapping is behind a live camera: this one is posed as a frame, not mapped
        state.merged_in_a_row += 1
        log.info("keyframe merged as a frame (mapping behind)", extra={"stream": msg.stream, "seq": msg.seq})
        return handle_frame_lite(state, msg, cfg)
    state.merged_in_a_row = 0
    guess = _pose_guess(state, msg.seq)  # a live keyframe starts where tracking put it (mapping may be far behind)
    guess = guess if msg.realtime else None
    early = state.early_codes.pop(msg.seq, None)
    codes, version = (msg.codes, msg.pca_version) if early is None else (early.codes, early.pca_version)
    native = None if codes is None else NativeCodes(version, codes)
    if native is not None and state.pca_version == -1:
        state.pca_version = msg.pca_version  # no basis yet: the first codes set the version
    codes = None if native is None else _in_current_version(state, native)
    if native is not None and codes is None:
        log.warning("codes of an unknown PCA basis left out of BA", extra={
            "stream": msg.stream, "seq": msg.seq, "pca_version": native.version, "current": state.pca_version})
    update = state.frontend.add_keyframe(KeyframeInput(msg.seq, msg.t_ns, msg.image, np.asarray(msg.intrinsics),
                                                       codes, msg.disparity_prior, native, guess, msg.realtime,
                                                       _defer(state, msg, cfg)))
    state.keyframes += 1
    state.last_seq = max(state.last_seq, msg.seq)
    return outputs_of(state.frontend, msg, update, final=False)


def _pose_guess(state: BaState, seq: int) -> torch.Tensor | None:
    """A keyframe's world_from_cam as tracking found it, moved with its reference if mapping has refined that."""
    anchor = _take_anchor(state, seq)
    if anchor is None:
        return None
    graph = state.frontend.graph
    if graph is not None and anchor.ref_seq in graph.seqs:
        return graph.poses[graph.index(anchor.ref_seq)] @ anchor.ref_from_cam.to(graph.device)
    return anchor.world_from_cam


def _take_anchor(state: BaState, seq: int) -> Anchor | None:
    """Pop frame ``seq``'s anchor, forgetting older ones mapping never asked for (frames dropped on the way)."""
    anchor = state.anchors.pop(seq, None)
    if len(state.anchors) > 64:
        for old in [s for s in list(state.anchors) if s < seq]:
            state.anchors.pop(old, None)
    return None if anchor is None else Anchor(*anchor)


def handle_codes(state: BaState, msg: KeyframeCodes, cfg: BaSettings) -> Outputs:
    """A keyframe's codes, after its geometry: from now on its edges use ARK (and the embedding term)."""
    if msg.pca_version not in state.bases:
        state.pca_fetch.want(msg.pca_version)
    if state.pca_version == -1:
        state.pca_version = msg.pca_version
    graph = state.frontend.graph
    if graph is not None and msg.seq in graph.seqs:
        k = graph.index(msg.seq)
        graph.native_codes[k] = NativeCodes(msg.pca_version, own_pages(msg.codes))
        graph.codes[k] = _as_tensor(_in_current_version(state, graph.native_codes[k]))
    elif graph is None or not graph.seqs or msg.seq > graph.seqs[-1]:
        state.early_codes[msg.seq] = msg  # its keyframe is still on the way (another key)
    return []


def _merge(state: BaState, msg: Keyframe, cfg: BaSettings) -> bool:
    """Real time, mapping behind: keyframes wait in the inbox. This one is merged as a frame unless that would
    leave more than ``realtime_max_merged`` in a row between mapped keyframes (tracking and the next keyframe's
    flow need them close enough)."""
    return (msg.realtime and state.frontend.initialised and state.keyframe_backlog >= cfg.realtime_keyframe_backlog
            and state.merged_in_a_row < cfg.realtime_max_merged)


def _defer(state: BaState, msg: Keyframe, cfg: BaSettings) -> bool:
    """Real time, keyframes waiting behind mapping: this one joins the graph aligned, its window BA left to a
    later keyframe (the frontend bounds how many in a row)."""
    return msg.realtime and state.keyframe_backlog >= cfg.realtime_defer_backlog


def handle_frame_lite(state: BaState, msg: FrameLite | Keyframe, cfg: BaSettings) -> Outputs:
    """A frame's mapped pose. Lossless: aligned to the keyframes around it once the next one exists (tracking's
    pose stands until then). Real time: anchored where tracking posed it, or interpolated between its keyframes
    when tracking did not; mapping spends no flow on frames, it has no time to spare."""
    state.last_seq = max(state.last_seq, msg.seq)
    anchor = _take_anchor(state, msg.seq)  # taken either way, so the table only holds frames still on their way
    live = anchor if msg.realtime else None
    tracked = None if live is None else (live.ref_seq, live.ref_from_cam)
    world = None if live is None else live.world_from_cam
    # a live frame tracking did not pose (before the map started, too little flow, or dropped to keep tracking's
    # latency bounded) is posed between its keyframes by time alone: aligning it by flow would put mapping
    # behind the camera
    cheap = msg.realtime and anchor is None
    flow = None if live is None or live.flow is None else (live.ref_seq, *live.flow)
    update = state.frontend.add_frame(FrameInput(msg.seq, msg.t_ns, msg.image, tracked, cheap, world, flow))
    return outputs_of(state.frontend, msg, update, final=False)


def _in_current_version(state: BaState, native: NativeCodes) -> np.ndarray | None:
    """(h, w, K) codes of ``native`` in ``state.pca_version``; None when either basis is unknown."""
    if native.version == state.pca_version:
        return native.codes
    source, target = state.bases.get(native.version), state.bases.get(state.pca_version)
    if source is None or target is None:
        return None
    return convert_codes(native.codes, code_map(source, target))


def handle_pca(state: BaState, msg: PcaBasis, cfg: BaSettings) -> Outputs:
    """Keep the basis; a newer version (or one that frees codes left out) re-codes the graph."""
    known = state.bases.get(msg.version)
    if known is not None and np.array_equal(known.mean, msg.mean) and np.array_equal(known.components, msg.components):
        return []
    log.info("pca basis", extra={"stream": msg.stream, "version": msg.version, "backbone": msg.backbone})
    state.bases[msg.version] = msg
    state.pca_version = max(state.pca_version, msg.version)
    graph = state.frontend.graph
    if graph is not None:
        dropped = graph.recode(lambda native: _as_tensor(_in_current_version(state, native)))
        if dropped:
            log.warning("keyframes without codes for BA", extra={"stream": msg.stream, "seqs": dropped[:10],
                                                                  "pca_version": state.pca_version})
    return []


def _as_tensor(codes: np.ndarray | None) -> torch.Tensor | None:
    return None if codes is None else torch.from_numpy(own_pages(np.asarray(codes, np.float32)))


def handle_eos(state: BaState, msg: Eos, cfg: BaSettings, publish: Callable[[Outputs], None] | None = None) -> Outputs:
    """Features ended: global BA, final graph and poses, then this stage's EOS; the state is reset. With
    ``publish``, the final graph goes out through it as soon as the BA settled it, so the mapstore exports the map
    while the frames are solved again; the rest is returned (all of it without ``publish``)."""
    if msg.stage != "features":
        return []
    log.info("end of stream: global BA", extra={"stream": msg.stream, "seq": msg.seq, "keyframes": state.keyframes})
    began = time.monotonic()
    settled: Outputs = []
    solved: Outputs = []
    try:
        settled = outputs_of(state.frontend, msg, state.frontend.settle_keyframes(), final=True)
        if publish is not None:
            publish(settled)
        poses = state.frontend.solve_frames().poses
        solved = [] if poses is None else [poses_out(msg.stream, msg.seq, msg.t_ns, poses, final=True)]
    except (ValueError, RuntimeError):  # the stream must still end downstream
        log.exception("global BA failed; last online state stands", extra={"stream": msg.stream, "seq": msg.seq})
        state.rejected["global_ba"] += 1
    lost, strayed = state.frontend.frames.lost_views(), state.frontend.frames.strayed()
    eos = Eos(msg.stream, max(state.last_seq, msg.seq), time.time_ns(), stage="ba", count=state.keyframes,
              reason=msg.reason, dropped=state.dropped, views_lost=np.array(lost, np.int64).reshape(-1, 2),
              frames_strayed=strayed, work_s=round(time.monotonic() - began, 3))
    log.info("stream done", extra={"stream": msg.stream, "keyframes": state.keyframes, "merged": state.merged,
                                   "dropped": state.dropped, "views_lost": len(lost),
                                   "frames_strayed": strayed, "keyframes_relocalised": state.frontend.relocalised})
    state.ended_upto = max(state.last_seq, msg.seq)
    ended = [(keys.topic(msg.stream, keys.EOS), eos)]
    state.final_outputs = settled + solved + ended  # for a mapstore that restarts
    state.frontend = Frontend(state.frontend.params, state.frontend.device)
    state.keyframes, state.keyframes_seen, state.last_seq, state.merged = 0, 0, -1, 0
    state.early_codes.clear()
    return solved + ended if publish is not None else state.final_outputs


HANDLERS = {Keyframe: handle_keyframe, FrameLite: handle_frame_lite, KeyframeCodes: handle_codes,
            PcaBasis: handle_pca}  # and Eos: handle_eos, which may also publish before it returns


def handle(state: BaState, msg: Message, cfg: BaSettings, publish: Callable[[Outputs], None] | None = None) -> Outputs:
    """The error boundary of one message: bad input is logged with its seq, counted, and the loop goes on.
    ``publish``: what an EOS sends before it returns (:func:`handle_eos`)."""
    if isinstance(msg, Keyframe):
        state.keyframes_seen += 1
    try:
        if isinstance(msg, Eos):
            return handle_eos(state, msg, cfg, publish)
        return HANDLERS[type(msg)](state, msg, cfg)
    except (ValueError, RuntimeError, KeyError, IndexError) as exc:
        state.rejected[msg.KIND] += 1
        log.warning("message rejected", extra={"stream": msg.stream, "seq": msg.seq, "kind": msg.KIND,
                                               "error": str(exc)})
        return []


def run(cfg: BaSettings, bus: Bus, stop: threading.Event, state: BaState | None = None) -> BaState:
    """Serve stream ``cfg.stream`` until ``stop`` is set: tracking on its own thread, mapping on this one. With
    ``checkpoint_dir`` set and a session known, the stream's state resumes from its checkpoint when there is one."""
    state = state or build_state(cfg)
    session = session_of(bus)  # None outside a host (a pinned service): no session, no checkpoint to resume
    checkpoints = Checkpointer(cfg.checkpoint_dir if session else "", cfg.stream, session, cfg.checkpoint_period_s)
    resumed_at = recovery.resume(state, checkpoints, cfg)
    consumer = consumer_name("ba", bus.instance)  # a new name per start: features sees a resumed ba
    topic = lambda name: keys.topic(cfg.stream, name)  # noqa: E731
    mapping = bus.inbox({topic(keys.PCA): [PcaBasis], topic(keys.CODES): [KeyframeCodes], topic(keys.EOS): [Eos]},
                        maxsize=cfg.inbox_size, droppable=(FrameLite,))
    track_box = Inbox(cfg.tracking_backlog, droppable=(FrameLite,))  # real time: stale frames make way

    def to_both(delivery: Delivery) -> None:  # frames and keyframes feed tracking and mapping alike
        for box in (track_box, mapping):
            box.lossless = not delivery.msg.realtime  # old frames are dropped only from real-time streams
            box.put(delivery)

    for name, kind in ((keys.KEYFRAME, Keyframe), (keys.FRAME_LITE, FrameLite)):
        bus.subscribe(topic(name), to_both, [kind])
    tracking = TrackingLoop(cfg.tracking_core(), bus, track_box, cfg.stream,
                            state.anchors, cfg.tracking_nice)
    restarted_mapstore = recovery.watch_mapstores(bus, topic(keys.PROGRESS))
    release = MemoryRelease(cfg.release_memory_period_s)
    mapstore_done = False
    tracking.start()
    if (ref := state.frontend.reference()) is not None:  # resumed: tracking starts from mapping's newest keyframe
        tracking.set_reference(ref)
    bus.ready()
    nice_this_thread(cfg.mapping_nice)
    sys.setswitchinterval(cfg.switch_interval_s)  # tracking's thread waits at most this for the interpreter
    log.info("ba ready", extra={"stream": cfg.stream, "device": str(state.frontend.device)})
    eos: tuple[Eos, float] | None = None  # features' EOS waiting for the keyframes still in flight
    next_progress = 0.0
    try:
        while not stop.is_set():
            if time.monotonic() >= next_progress:
                bus.publish(topic(keys.PROGRESS), Credit(cfg.stream, state.last_seq, time.time_ns(), consumer=consumer,
                                                         checkpoints=checkpoints.enabled,
                                                         durable=checkpoints.durable))
                next_progress = time.monotonic() + PROGRESS_PERIOD_S
            delivery = mapping.get(POLL_S)
            # a live camera's frames reach mapping too, so its inbox is never empty for long: between them is
            # mapping's spare time. A tracking thread in this interpreter needs it at once for every frame; a
            # tracking process does not
            live_frame = delivery is not None and isinstance(delivery.msg, FrameLite) and delivery.msg.realtime
            if delivery is None or (live_frame and tracking.in_process):
                waits_for = (mapping,) if tracking.in_process else (mapping, track_box)
                for key, out in refine_while_idle(state, waits_for, cfg):
                    bus.publish(key, out)
            msg = delivery.msg if delivery is not None else None
            if isinstance(msg, Eos) and msg.stage == "features":
                eos, msg = (msg, time.monotonic() + cfg.eos_wait_s), None
            if isinstance(msg, (Keyframe, FrameLite)) and recovery.seen_before(state, msg, resumed_at):
                msg = None  # sent again (to a consumer that resumed), or in flight when ba was killed
            if isinstance(msg, Eos) and msg.stage == "mapstore":
                mapstore_done = True
            if restarted_mapstore.is_set() and state.final_outputs:  # it may have missed the end: send it again
                restarted_mapstore.clear()
                for key, out in state.final_outputs:
                    bus.publish(key, out)
            hold(bus, bool(state.final_outputs) and not mapstore_done)
            if msg is not None:
                state.keyframe_backlog = mapping.count(Keyframe)
                began = time.monotonic()
                for key, out in handle(state, msg, cfg):
                    bus.publish(key, out)
                if isinstance(msg, Keyframe):
                    log.debug("keyframe handled", extra={"stream": msg.stream, "seq": msg.seq,
                                                         "backlog": state.keyframe_backlog,
                                                         "seconds": round(time.monotonic() - began, 3)})
                if isinstance(msg, Keyframe) and cfg.mapping_min_seconds > 0:
                    stop.wait(max(0.0, began + cfg.mapping_min_seconds - time.monotonic()))
                if isinstance(msg, Keyframe):
                    next_progress = 0.0
                    ref = state.frontend.reference()
                    if ref is not None:
                        tracking.set_reference(ref)
                    # when due; idle mapping runs it anyway; not with the stream's end queued (its BA comes next)
                    if cfg.background_ba_when_busy and not msg.realtime and mapping.qsize() and not mapping.count(Eos):
                        for key, out in refine_globally(state):
                            bus.publish(key, out)
                    if checkpoints.due():
                        checkpoints.save(state)
                    release.maybe()  # between two keyframes' BAs: no temporaries alive
                if isinstance(msg, Keyframe) and msg.codes is not None and msg.pca_version not in state.bases:
                    state.pca_fetch.want(msg.pca_version)
            state.pca_fetch.run_due(bus, cfg.stream, state.bases, lambda basis: handle(state, basis, cfg))
            if eos is not None and (recovery.stream_complete(state, eos[0], mapping.qsize())
                                    or time.monotonic() > eos[1]):
                state.dropped = mapping.dropped + track_box.dropped

                def publish_settled(outputs: Outputs) -> None:
                    for key, out in outputs:
                        bus.publish(key, out)
                    # the settling BA's temporaries are dead: the heap the allocator kept for them goes back while
                    # the mapstore exports the map (at 2,000 frames ba held 1.15 GB through its export, 0.8 before)
                    release.now()

                ended = handle(state, eos[0], cfg, publish=publish_settled)
                release.now()  # the frames' solves and the stream's graph, before this stage's EOS says it is done
                for key, out in ended:
                    bus.publish(key, out)
                tracking.reset()
                eos = None
                if checkpoints.enabled:
                    log.info("checkpoints", extra={"stream": cfg.stream, "written": checkpoints.written,
                                                   "seconds": round(checkpoints.seconds, 2)})
                checkpoints.remove()  # the session's stream is done: nothing to resume
    finally:
        tracking.stop()
    return state
