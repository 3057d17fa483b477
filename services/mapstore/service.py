"""Mapstore service: keyframe / codes / pca / graph / eos in, queryables on ``kmvipe/<s>/map/**`` out.

One handler per message kind (`handle_<kind>(state, msg, cfg)`); `run` only receives, handles and serves.

A keyframe coded with a PCA basis version that no ``pca`` message brought (missed while down, or lost) is held;
`run` asks features' ``pca`` queryable for that version (`BasisFetch`: once, then again every ``retry_s`` while
it fails) and feeds the reply through `handle_pca`, like a ``pca`` message.

A keyframe's geometry comes first (``Keyframe`` without codes) and its codes later (``KeyframeCodes`` on
``kmvipe/<s>/codes``): the keyframe is fused for geometry at once and re-fused with its codes when they come
(`MapState.add_codes`). After every keyframe, and as a heartbeat every ``PROGRESS_S``, `run` reports the highest
keyframe seq it has committed on ``kmvipe/<s>/progress`` (a ``Credit``): features holds ingest back while the
mapstore is behind, so in lossless mode nothing queues without bound. The inbox is lossless: every message kind
the mapstore takes (keyframes, codes, graphs, bases, EOS) is essential.
"""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path

import numpy as np

from services.common import keys
from services.common.bus import Bus
from services.common.errors import DecodeError, ServiceTimeout
from services.common.lifecycle import MemoryRelease, Period, nice_this_thread
from services.common.pca_fetch import BasisFetch
from services.common.restarts import consumer_name
from services.common.streams import session_of
from services.common.schema import (Credit, Eos, Graph, Keyframe, KeyframeCodes, Message, PcaBasis as PcaMessage,
                                    Poses, decode)
from services.mapstore.archive import ArchivedMaps
from services.mapstore.config import MapstoreSettings
from services.mapstore.core.keyframe import KeyframeDepth
from services.mapstore.core.scoring import PcaBasis
from services.mapstore.colmap import ColmapImage, ColmapParams
from services.mapstore.export import ExportWriter, image_name, is_rigid
from services.mapstore.state import MapState

log = logging.getLogger(__name__)
POLL_S = 0.1
PCA_FETCH_TIMEOUT_S = 1.0
PROGRESS_S = 0.15  # heartbeat of the progress reports (features forgets a consumer silent for its credit TTL)


def handle_keyframe(state: MapState, msg: Keyframe, cfg: MapstoreSettings) -> None:
    """Commit and fuse a keyframe; without codes (they follow in a ``KeyframeCodes``) for geometry only. A
    keyframe already committed (sent again to a consumer that resumed) is left as it is."""
    if msg.seq in state.map.contents or state.map.is_folded(msg.seq):
        return
    state.add_keyframe(msg.seq, msg.t_ns, msg.image, msg.codes, msg.intrinsics, msg.pca_version, msg.realtime)


def handle_codes(state: MapState, msg: KeyframeCodes, cfg: MapstoreSettings) -> None:
    """The codes of keyframe ``msg.seq``: commit them and re-fuse it with them (they wait for a keyframe or basis
    that has not come yet)."""
    state.add_codes(msg.seq, msg.pca_version, msg.codes)


def handle_pca(state: MapState, msg: PcaMessage, cfg: MapstoreSettings) -> None:
    state.add_basis(PcaBasis(msg.version, np.array(msg.mean), np.array(msg.components), msg.backbone))


def handle_graph(state: MapState, msg: Graph, cfg: MapstoreSettings) -> None:
    began = time.monotonic()
    poses = {int(k): np.array(p) for k, p in zip(msg.kf_seqs, msg.poses)}
    depths = {}
    for i, kf_id in enumerate(msg.updated_seqs.tolist()):
        if msg.disparities is None:
            break
        depths[kf_id] = KeyframeDepth(
            np.array(msg.disparities[i]), np.array(msg.intrinsics),
            None if msg.static_weights is None else np.array(msg.static_weights[i]),
            None if msg.confidence is None else np.array(msg.confidence[i]))
    refreshed = state.update_graph(poses, depths, msg.metric)
    if msg.final:  # its re-fusion is part of the end of stream (what the export waits for)
        state.final_keyframes = {int(k) for k in msg.kf_seqs}
    log.log(logging.INFO if msg.final else logging.DEBUG, "graph applied", extra={
        "stream": msg.stream, "seq": msg.seq, "final": msg.final, "keyframes_refreshed": refreshed,
        "seconds": round(time.monotonic() - began, 2)})


def handle_eos(state: MapState, msg: Eos, cfg: MapstoreSettings) -> list[tuple[str, Message]]:
    """Upstream's end of stream: once ba's final graph is in (Zenoh orders messages per key only, so the EOS
    can overtake it), export the map and forward the EOS (the runner waits for it)."""
    if msg.stage != cfg.upstream:
        return []
    if not stream_complete(state):
        state.pending_eos, state.eos_deadline = msg, time.monotonic() + cfg.eos_wait_s
        return []
    return finish_stream(state, msg, cfg)


def stream_complete(state: MapState) -> bool:
    """ba's final graph is in, and so is every keyframe it names (keyframes come from features, on another key)
    with its codes and the PCA basis they were coded with (the ``codes`` and ``pca`` keys may lag behind the
    keyframe) — except codes of a real-time stream's keyframes, which the backbone may have skipped. A folded
    keyframe is final (ba's final graph names only the keyframes it still holds, which are never folded)."""
    with state.lock:
        if state.final_keyframes is None:
            return False
        held = set(state.map.held)

        def done(k: int) -> bool:
            content = state.map.contents.get(k)
            if content is None:
                return state.map.is_folded(k)
            return k not in held and (content.has_codes or k in state.realtime)

        return all(done(k) for k in state.final_keyframes)


def export_final(state: MapState, cfg: MapstoreSettings) -> None:
    """ba's final graph is in and the stream complete: the export, before ba's EOS (ba solves its frames again
    meanwhile; the export needs only the keyframes). Its seconds go into this stage's EOS."""
    began = time.monotonic()
    # the final graph and the last codes may wait (refresh_period_s, or in this batch)
    re_fused = state.refresh(now=True)
    fused_s = time.monotonic() - began
    try:
        if cfg.export_dir:
            export_state(state, Path(cfg.export_dir))
    except (ValueError, LookupError, ArithmeticError, OSError):  # the stream still ends, the map is in the store
        log.exception("export failed", extra={"stream": cfg.stream, "export_dir": cfg.export_dir})
    state.final_export_s = time.monotonic() - began
    log.info("map exported on ba's final graph",
             extra={"stream": cfg.stream, "seconds": round(state.final_export_s, 2), "keyframes_re_fused": re_fused,
                    "re_fusion_s": round(fused_s, 2)})


def finish_stream(state: MapState, msg: Eos, cfg: MapstoreSettings) -> list[tuple[str, Message]]:
    began = time.monotonic()
    log.info("end of stream", extra={"stream": msg.stream, "seq": msg.seq, "stage": msg.stage,
                                     "keyframes_without_codes": state.without_codes_count(),
                                     "keyframes_folded": state.map.folded_count, "late_codes": state.late_codes,
                                     "voxels_snapped": state.map.snapped_voxels,
                                     "exported_before": state.final_export_s is not None,
                                     "re_fusions": state.re_fusion["refreshes"],
                                     "keyframes_re_fused": state.re_fusion["keyframes"],
                                     "re_fusion_s": round(state.re_fusion["seconds"], 1)})
    if state.final_export_s is None:  # ba's EOS came first, or eos_wait_s passed: export the map as it is
        export_final(state, cfg)
    state.pending_eos, state.final_keyframes = None, None
    work_s = time.monotonic() - began + state.final_export_s
    state.final_export_s = None
    state.store.set_meta({"finished": "1"})  # nothing to resume after a restart
    count = state.keyframe_count()
    return [(keys.topic(msg.stream, keys.EOS), Eos(msg.stream, msg.seq, time.time_ns(), stage="mapstore", count=count,
                                                    work_s=round(work_s, 3)))]


def export_state(state: MapState, out: Path):
    """Write map.ply, depth maps, COLMAP cameras and keyframe images of the current map to `out`: the keyframes
    are read from the store a page at a time (folded ones are only there), live ones as the map holds them. The
    depth maps and images of keyframes that folded into ``export_dir`` during the stream are there already
    (:meth:`MapState.export_folded`): only their cameras and observations join the COLMAP model, at most
    ``colmap_points_per_image`` each."""
    with state.lock:
        fused = state.map.fused()
        colmap = ColmapParams(max_points_per_image=state.cfg.colmap_points_per_image)
        writer = ExportWriter(out, fused.xyz, fused.colours, state.metric, colmap=colmap)
        for records, _ in state.store.iter_keyframes(codes=False):
            for r in records:
                k = r.kf_id
                if state.map.is_folded(k):
                    content, depth, pose = r.content, r.depth, r.pose
                else:
                    content, depth, pose = state.map.contents.get(k), state.map.depths.get(k), state.map.poses.get(k)
                if content is None or depth is None or pose is None:
                    continue
                camera = None
                if is_rigid(pose):  # a diverged BA can publish such a pose; leave the camera out, not the export
                    h, w = content.image_hw
                    camera = ColmapImage(image_name(k), pose, np.asarray(depth.intrinsics), (w, h))
                else:
                    log.warning("camera with an invalid pose left out of the export", extra={"seq": k})
                written = state.folded_exports.written.get(k) if Path(out) == state.folded_exports.out else None
                if written is not None and written.metric == state.metric:
                    writer.add_written(k, depth, camera, written.image)
                else:
                    writer.add(k, depth, camera, state.store.image(k) if camera is not None else None)
        return writer.close()


HANDLERS = {Keyframe: handle_keyframe, KeyframeCodes: handle_codes, PcaMessage: handle_pca, Graph: handle_graph,
            Eos: handle_eos}


def handle(state: MapState, msg: Message, cfg: MapstoreSettings) -> list[tuple[str, Message]]:
    """Handle one message; returns the messages to publish."""
    return _guarded(HANDLERS[type(msg)], state, msg, cfg)


def _guarded(handler, state: MapState, msg: Message, cfg: MapstoreSettings) -> list[tuple[str, Message]]:
    """The error boundary of one message: bad input is logged with its seq and the loop goes on."""
    try:
        return handler(state, msg, cfg) or []
    except (ValueError, KeyError, LookupError, ArithmeticError) as exc:
        log.warning("message rejected", extra={"stream": msg.stream, "seq": msg.seq, "kind": msg.KIND,
                                               "error": f"{type(exc).__name__}: {exc}"})
        return []


def _fetch_current_basis(state: MapState, bus: Bus, cfg: MapstoreSettings) -> None:
    """A (re)started mapstore asks features for the PCA basis it may have missed while down."""
    try:
        reply = bus.request(keys.topic(cfg.stream, keys.PCA), timeout=PCA_FETCH_TIMEOUT_S, service="features")
        handle(state, decode(reply, PcaMessage), cfg)
    except (ServiceTimeout, RuntimeError, DecodeError) as exc:
        log.info("no PCA basis from features yet (it will come on the pca topic)", extra={"reason": str(exc)})


def _held_versions(state: MapState) -> set[int]:
    """Basis versions of the keyframes held for want of their basis (e.g. stored before a restart)."""
    with state.lock:
        return {state.map.contents[k].pca_version for k in state.map.held}


def progress_report(state: MapState, cfg: MapstoreSettings, consumer: str) -> tuple[str, Credit]:
    """The progress report: ``seq`` = the highest keyframe seq committed (features counts the keyframes it
    published above it as the mapstore's backlog)."""
    committed = state.committed_seq()  # committed is durable: the database is the mapstore's checkpoint
    return keys.topic(cfg.stream, keys.PROGRESS), Credit(cfg.stream, committed, time.time_ns(), consumer=consumer,
                                                         checkpoints=True, durable=committed)


def _wanted_version(state: MapState, msg: Message) -> int | None:
    """The basis version a keyframe or codes message needs that the mapstore lacks, if any."""
    if isinstance(msg, (Keyframe, KeyframeCodes)) and msg.codes is not None and msg.pca_version not in state.bases:
        return msg.pca_version
    return None


def run(cfg: MapstoreSettings, bus: Bus, stop: threading.Event, state: MapState | None = None,
        fetch: BasisFetch | None = None) -> MapState:
    """Serve the map of `cfg.stream` until `stop` is set. ``fetch``: the missing-basis requests (counts)."""
    state, fetch = state or MapState(cfg, session_of(bus)), fetch or BasisFetch()
    topic = lambda name: keys.topic(cfg.stream, name)  # noqa: E731
    inbox = bus.inbox({topic(keys.KEYFRAME): [Keyframe], topic(keys.CODES): [KeyframeCodes],
                       topic(keys.PCA): [PcaMessage], topic(keys.GRAPH): [Graph], topic(keys.EOS): [Eos]},
                      lossless=True, droppable=())  # every kind is essential: credit bounds the queue, not drops
    consumer = consumer_name("mapstore", bus.instance)  # a new name per start: features sees a restart
    bus.subscribe(topic(keys.POSE), lambda d: state.pose_log.add(d.msg), [Poses])  # the closure follows rebinding
    archives = ArchivedMaps(cfg)  # earlier sessions' maps, served with ?session=<id>
    bus.serve(keys.map_key(cfg.stream, "**"),
              lambda key, params, payload: archives.answer(state, cfg.stream, key, params, payload))
    bus.ready()
    _fetch_current_basis(state, bus, cfg)
    for version in _held_versions(state):
        fetch.want(version)
    nice_this_thread(cfg.fusion_nice)  # the stream's own thread: queries and the bus keep their priority
    log.info("mapstore serving", extra={"stream": cfg.stream})
    last_report = 0.0
    release = MemoryRelease(cfg.release_memory_period_s)
    # what messages change is re-fused at most once per period: every graph update moves ba's window again, and
    # re-fusing after each one took the mapstore a third of the machine on a lossless KITTI run (docs/BENCHMARKS.md)
    refresh = Period(cfg.refresh_period_s)
    carried = None  # a message of another session that ended a batch: the first of the next one
    while not stop.is_set():
        delivery, carried = carried or inbox.get(min(POLL_S, PROGRESS_S)), None
        if delivery is not None:
            state = state.for_session(delivery.msg.session)  # the queryable's closure follows the rebinding
            with state.batch(refresh=False):
                for n in range(cfg.refresh_batch):
                    if n and (delivery := inbox.get(0)) is None:
                        break
                    if delivery.msg.session not in ("", state.session):
                        carried = delivery
                        break
                    for key, out in handle(state, delivery.msg, cfg):
                        bus.publish(key, out)
                    msg = delivery.msg
                    if (version := _wanted_version(state, msg)) is not None:
                        fetch.want(version)
                    if isinstance(msg, Keyframe):  # committed (fused at the next re-fusion): report at once
                        bus.publish(*progress_report(state, cfg, consumer))
                        last_report = time.monotonic()
        if refresh.due():
            began = time.monotonic()
            state.refresh()  # what the batches since the last re-fusion changed
            refresh.hold_after(time.monotonic() - began, cfg.refresh_max_share)
            release.maybe()  # between re-fusions: their arrays are freed
        if time.monotonic() - last_report >= PROGRESS_S:  # heartbeat: the next one repeats it, no need to block
            bus.publish(*progress_report(state, cfg, consumer), drop_if_congested=True)
            last_report = time.monotonic()
        fetch.run_due(bus, cfg.stream, state.bases, lambda basis: handle(state, basis, cfg))
        if state.pose_log.due():
            state.pose_log.flush(state.store)
        if state.final_keyframes is not None and state.final_export_s is None and stream_complete(state):
            export_final(state, cfg)
        held = state.pending_eos
        if held is not None and (stream_complete(state) or time.monotonic() > state.eos_deadline):
            for key, out in _guarded(finish_stream, state, held, cfg):
                bus.publish(key, out)
    state.pose_log.flush(state.store)
    state.refresh()  # the map handed back holds everything committed
    archives.close()
    return state
