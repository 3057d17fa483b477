"""Features service: ``frame`` in; ``keyframe`` / ``frame_lite`` / ``codes`` / ``pca`` / ``eos`` out;
``credit`` back to ingest; ``intrinsics`` from ba refine the focal-length guess; ``progress`` from ba and the
mapstore hold a lossless stream back. One handler per message kind; ``run`` only receives, handles and publishes.

A keyframe's geometry goes out at once (``Keyframe`` without codes); its DINO codes follow in a ``codes``
message from the semantics thread (services/features/semantics.py), so the frame path never waits for the
backbone. Lossless credit covers every stage: ingest gets none while the backbone, ba or the mapstore are more
than a few messages behind; in real time nothing is held back and stale keyframes go without codes (counted).

The ``pca`` key is also a queryable over every basis version published in this run (``?version=<n>``; the
latest without a selector), so a consumer that missed one (late join, restart, lost message) can fetch it."""
from __future__ import annotations

import logging
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass, field

import cv2
import numpy as np

from ..common import keys
from ..common.bus import Bus, Inbox
from ..common.models.backbones import normalise_rgb
from ..common.lifecycle import release_free_memory
from ..common.models.loaders import load_backbone, load_depth_model
from ..common.models.store import ModelStore
from ..common.schema import Credit, Eos, Frame, FrameLite, Intrinsics, Keyframe, KeyframeCodes, Message, PcaBasis
from ..common.restarts import consumer_name
from ..common.streams import hold
from .replay import ReplayBuffer
from .config import FeaturesSettings
from .core.geometry import Intrinsics as K4
from .core.pca import PcaBasis as CoreBasis
from .core.pipeline import CodeQueue, FeaturesCore, KeyframeOut, LiteOut
from .oracle import ORACLE_BACKBONE, SynthOracleBackbone
from .semantics import SemanticsWorker, load_at_niceness

log = logging.getLogger(__name__)
POLL_S = 0.05
CREDIT_PERIOD_S = 0.1
VERSION_PARAM = "version"  # selector parameter of the pca queryable: kmvipe/<s>/pca?version=<n>

Outputs = list[tuple[str, Message]]


@dataclass
class FeaturesState:
    core: FeaturesCore
    semantics: SemanticsWorker
    stream: str
    last_seq: int = -1  # highest frame seq handled (credit is granted beyond it)
    last_keyframe_seq: int = -1
    last_frame: tuple[int, int, int] = (0, 0, 0)  # original (width, height, t_ns) of the latest frame
    frames_seen: int = 0
    # the first frame this worker answers for: after the last one a predecessor handled (Frame.features_handled;
    # > 0 after a restart, when ingest sent again what it lost), so frames lost before the first one seen count
    first_seq: int = -1
    realtime: bool = False  # the stream is paced in real time (from its frames)
    pending_eos: Eos | None = None  # ingest's EOS, held until every frame it announced has arrived
    eos_deadline: float = 0.0
    closing: Eos | None = None  # the stream ended: its EOS goes out once the semantics thread is done
    basis: CoreBasis | None = None  # the latest basis
    # every basis published in this run, by version, for the pca queryable (K x D float32: ~100 KB at K = 32,
    # D = 768, so ~5 MB for the ~50 versions of a KITTI drive)
    bases: dict[int, CoreBasis] = field(default_factory=dict)
    published: int = 0  # keyframes published in this stream
    bad_frames: int = 0
    dropped: int = 0  # frames the inbox dropped by the real-time policy (set at end of stream)
    stamps: dict[int, int] = field(default_factory=dict)  # keyframe seq -> t_ns, until its codes leave
    # downstream progress: consumer -> (highest frame seq it handled, when it said so); and what was published
    # since, as (seq, is_keyframe), to count how far each one is behind
    downstream: dict[str, tuple[int, float]] = field(default_factory=dict)
    sent: deque = field(default_factory=deque)
    inbox: Inbox | None = None  # the service loop's, whose real-time drops count for this stream
    # sent to ba since its last checkpoint, and to the mapstore since its last commit
    replays: tuple[ReplayBuffer, ...] = field(default_factory=lambda: (
        ReplayBuffer("ba-", (Keyframe, FrameLite), eos=True), ReplayBuffer("mapstore-", (Keyframe,), eos=False)))
    started: float = field(default_factory=time.monotonic)  # when this stream's state was made


def load_models(cfg: FeaturesSettings) -> tuple:
    """(backbone, depth model or None) named in the settings, loaded once per process and shared by every stream
    (one clear ModelError if one is missing)."""
    store = ModelStore(cfg.models_dir)
    if cfg.backbone == ORACLE_BACKBONE:  # test double: exact synthetic-world labels instead of a model
        backbone = SynthOracleBackbone(cfg.oracle_params())
    else:  # loaded at the semantics thread's priority, so the runtime's own threads run at it too
        backbone = load_at_niceness(
            lambda: load_backbone(cfg.backbone, store, cfg.device, cfg.runtime, cfg.threads, cfg.half,
                                  cfg.runtime_spinning, cfg.runtime_int8),
            cfg.semantics_nice)
    depth = load_depth_model(cfg.depth_model, store, cfg.device, cfg.half) if cfg.depth_model else None
    if "torch" in sys.modules:  # a model runs in torch (the CPU path, onnxruntime and the oracle, never loads it)
        sys.modules["torch"].set_num_threads(cfg.threads)
    # parsing, cutting and compiling the ONNX graph leaves ~250 MB of freed heap the allocator would keep for good
    # (DINOv2 ViT-S/14: 765 -> 503 MB)
    release_free_memory()
    return backbone, depth


def build_state(cfg: FeaturesSettings, models: tuple | None = None) -> FeaturesState:
    """One stream's state around ``models`` (:func:`load_models`; loaded here when not given)."""
    backbone, depth = models if models is not None else load_models(cfg)
    on_cuda = getattr(backbone, "device_type", "cpu") == "cuda"
    core = FeaturesCore(cfg.params(getattr(backbone, "patch_size", 14), on_cuda), backbone, normalise_rgb, depth)
    semantics = SemanticsWorker(core, CodeQueue(core.params.pca, backbone.output_space), cfg.semantics_nice, cfg.stream)
    return FeaturesState(core, semantics, cfg.stream)


def decode_image(msg: Frame) -> np.ndarray:
    """(H, W, 3) uint8 RGB of a frame message; ValueError if its JPEG is corrupt."""
    if msg.image is not None:
        return msg.image
    bgr = cv2.imdecode(np.frombuffer(msg.jpeg, np.uint8), cv2.IMREAD_COLOR)
    if bgr is None or bgr.shape[:2] != (msg.height, msg.width):
        raise ValueError("JPEG payload does not decode to the announced size")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def handle_frame(state: FeaturesState, msg: Frame, cfg: FeaturesSettings) -> Outputs:
    outputs = _frame(state, msg, cfg)
    state.frames_seen += 1
    if state.first_seq < 0:  # min: the repeat of a frame its predecessor handled, sent to say where the stream is
        state.first_seq = min(msg.seq, msg.features_handled + 1)
    if state.pending_eos is not None and _all_frames_in(state, state.pending_eos):
        outputs += _finish(state, state.pending_eos)
    return outputs


def _frame(state: FeaturesState, msg: Frame, cfg: FeaturesSettings) -> Outputs:
    state.last_seq = max(state.last_seq, msg.seq)
    state.last_frame = (msg.width, msg.height, msg.t_ns)
    state.realtime = msg.realtime
    try:
        image = decode_image(msg)
    except ValueError as exc:
        state.bad_frames += 1
        log.warning("corrupt frame skipped", extra={"stream": msg.stream, "seq": msg.seq, "error": str(exc)})
        return []
    hint = K4(*map(float, msg.intrinsics)) if msg.intrinsics is not None else None
    out = state.core.process(msg.seq, image, hint, None if msg.depth is None else np.asarray(msg.depth))
    if isinstance(out, LiteOut):
        lite = FrameLite(msg.stream, msg.seq, msg.t_ns, image=out.grey, intrinsics=np.array(out.intrinsics, np.float64),
                         ref_seq=state.last_keyframe_seq, realtime=msg.realtime)
        state.sent.append((msg.seq, False))
        return [(keys.topic(msg.stream, keys.FRAME_LITE), lite)]
    state.last_keyframe_seq = out.seq
    return _keyframe(state, msg.stream, out, msg.width, msg.height, msg.t_ns)


def _keyframe(state: FeaturesState, stream: str, kf: KeyframeOut, width: int, height: int, t_ns: int) -> Outputs:
    """The keyframe's geometry now; its codes once the semantics thread has described it."""
    disparity = None if kf.disparity is None else kf.disparity.astype(np.float32)
    message = Keyframe(stream, kf.seq, t_ns, image=kf.image, intrinsics=np.array(kf.intrinsics, np.float64),
                       orig_width=width, orig_height=height, disparity_prior=disparity, realtime=state.realtime)
    state.published += 1
    state.sent.append((kf.seq, True))
    state.stamps[kf.seq] = t_ns
    state.semantics.submit(kf, state.realtime)
    return [(keys.topic(stream, keys.KEYFRAME), message)] + coded_outputs(state)


def handle_intrinsics(state: FeaturesState, msg: Intrinsics, cfg: FeaturesSettings) -> Outputs:
    state.core.intrinsics.refine(K4(*map(float, msg.intrinsics)), msg.width, msg.height)
    return []


def handle_eos(state: FeaturesState, msg: Eos, cfg: FeaturesSettings) -> Outputs:
    """Ingest ended: finish once every frame it sent has arrived (see ``eos_wait_s``)."""
    for replay in state.replays:  # a consumer that finished will not resume: what was kept for it is done
        if msg.stage == replay.prefix.rstrip("-"):
            replay.finished = True
    if msg.stage != "ingest":
        return []
    if _all_frames_in(state, msg):  # frames the inbox dropped (real time) are not coming
        return _finish(state, msg)
    state.pending_eos, state.eos_deadline = msg, time.monotonic() + cfg.eos_wait_s
    return []


def _all_frames_in(state: FeaturesState, eos: Eos) -> bool:
    """Every frame ingest announced has arrived, counting from the first this worker answers for (a features that
    restarted mid-stream gets the frames its predecessor had not handled, not the whole stream)."""
    return state.frames_seen + state.dropped >= eos.count - max(state.first_seq, 0)


def overdue_eos(state: FeaturesState) -> Outputs:
    """Finish a held EOS whose frames did not all come within ``eos_wait_s`` (some were lost upstream)."""
    if state.pending_eos is None or time.monotonic() < state.eos_deadline:
        return []
    log.warning("end of stream with frames missing", extra={"stream": state.stream, "seen": state.frames_seen,
                                                           "announced": state.pending_eos.count})
    return _finish(state, state.pending_eos)


def _finish(state: FeaturesState, msg: Eos) -> Outputs:
    """The last frame becomes a keyframe, the semantics thread finishes its queue, then the EOS goes on."""
    state.pending_eos = None
    outputs: Outputs = []
    last = state.core.promote_last()
    if last is not None:
        width, height, t_ns = state.last_frame
        outputs += _keyframe(state, msg.stream, last, width, height, t_ns)
    state.semantics.flush()
    state.closing = msg
    return outputs + closing_outputs(state)


def closing_outputs(state: FeaturesState) -> Outputs:
    """Codes ready now and, once the semantics thread is idle after the end of stream, this stage's EOS."""
    outputs = coded_outputs(state)
    msg = state.closing
    if msg is None or not state.semantics.idle():
        return outputs
    outputs += coded_outputs(state)  # what finished between the first look and the idle check
    lost = max(0, msg.count - max(state.first_seq, 0) - state.frames_seen - state.dropped)
    eos = Eos(msg.stream, msg.seq, time.time_ns(), stage="features", count=state.published, reason=msg.reason,
              dropped=state.dropped, codes_skipped=state.semantics.skipped, lost=lost)
    state.frames_seen, state.published, state.closing = 0, 0, None  # a new stream may follow on the same key
    state.first_seq = -1
    state.dropped = 0
    if state.inbox is not None:
        state.inbox.dropped_by_kind.clear()
    state.semantics.skipped = 0
    state.sent.clear()
    return outputs + [(keys.topic(msg.stream, keys.EOS), eos)]


def coded_outputs(state: FeaturesState) -> Outputs:
    """``pca`` (a new basis first) and ``codes`` messages for what the semantics thread has finished."""
    outputs: Outputs = []
    for basis, ready in state.semantics.take():
        if basis is not None:
            state.basis = basis
            state.bases[basis.version] = basis
            outputs.append((keys.topic(state.stream, keys.PCA), pca_message(state.stream, basis, ready[0][0].seq if ready else 0)))
        for kf, codes in ready:
            t_ns = state.stamps.pop(kf.seq, 0)
            outputs.append((keys.topic(state.stream, keys.CODES), KeyframeCodes(
                state.stream, kf.seq, t_ns, pca_version=state.basis.version, codes=codes)))
            log.debug("keyframe codes", extra={"stream": state.stream, "seq": kf.seq,
                                               **{k: round(v, 3) for k, v in kf.seconds.items()}})
    return outputs


def credit_limit(state: FeaturesState, cfg: FeaturesSettings, now: float) -> int:
    """Highest frame seq ingest may send. In lossless mode nothing beyond what is handled while the backbone or
    a live downstream stage (ba, mapstore: their ``progress``) is too far behind; in real time, no hold."""
    hold = state.last_seq
    # a stream served by every-stream services: its ba and mapstore workers start when the source announces it,
    # as this one does; the first frames wait until they have said they are there (or for downstream_wait_s)
    missing = [name for name in cfg.await_downstream if not any(c.startswith(f"{name}-") for c in state.downstream)]
    if missing and now - state.started < cfg.downstream_wait_s:
        return hold
    if state.realtime:
        return hold + cfg.credit_window
    if state.semantics.backlog() >= cfg.codes_backlog:
        return hold
    for consumer, (seq, seen) in list(state.downstream.items()):
        if now - seen > cfg.downstream_ttl_s:
            continue
        keyframes = sum(1 for s, is_kf in state.sent if s > seq and is_kf)
        if consumer.startswith("mapstore"):
            if keyframes >= cfg.downstream_keyframes:
                return hold
        elif keyframes >= cfg.ba_keyframes or sum(1 for s, _ in state.sent if s > seq) >= cfg.downstream_frames:
            return hold
    while state.sent and len(state.sent) > 4 * cfg.downstream_frames:  # older entries no longer count
        state.sent.popleft()
    return hold + cfg.credit_window


def on_progress(state: FeaturesState, msg: Credit) -> None:
    """A downstream stage's progress report (Zenoh thread: dict assignments)."""
    for replay in state.replays:  # a consumer that resumed from its durable state replaces the killed one
        for gone in replay.on_progress(msg):
            state.downstream.pop(gone, None)
    state.downstream[msg.consumer] = (msg.seq, time.monotonic())


def pca_message(stream: str, basis: CoreBasis, seq: int = 0) -> PcaBasis:
    return PcaBasis(stream, seq, time.time_ns(), version=basis.version, backbone=basis.backbone,
                    mean=basis.mean.astype(np.float32), components=basis.components.astype(np.float32),
                    explained_variance=basis.explained_variance.astype(np.float32))


HANDLERS = {Frame: handle_frame, Intrinsics: handle_intrinsics, Eos: handle_eos}


def run(cfg: FeaturesSettings, bus: Bus, stop: threading.Event, state: FeaturesState | None = None) -> FeaturesState:
    state = state or build_state(cfg)
    topic = lambda name: keys.topic(cfg.stream, name)  # noqa: E731
    inbox = bus.inbox({topic(keys.FRAME): [Frame], topic(keys.INTRINSICS): [Intrinsics], topic(keys.EOS): [Eos]},
                      maxsize=4 * cfg.credit_window + 16, droppable=(Frame,))
    state.inbox = inbox
    bus.subscribe(topic(keys.PROGRESS), lambda d: on_progress(state, d.msg), [Credit])
    # late joiners (a restarted mapstore) ask for the current basis, consumers that missed one for its version
    bus.serve(topic(keys.PCA), lambda key, params, payload: answer_pca(state, params))
    state.semantics.start()
    bus.ready()
    log.info("features ready", extra={"stream": cfg.stream, "backbone": cfg.backbone})
    next_credit = 0.0
    # a new name per start, so ingest sees a restart; what it handled went on to ba and the mapstore, which keep it
    consumer = consumer_name("features", bus.instance)
    try:
        while not stop.is_set():
            now = time.monotonic()
            if now >= next_credit:  # credit doubles as a heartbeat, so ingest knows we are alive
                bus.publish(topic(keys.CREDIT), Credit(cfg.stream, credit_limit(state, cfg, now), time.time_ns(),
                                                       consumer=consumer, checkpoints=True, durable=state.last_seq))
                next_credit = now + CREDIT_PERIOD_S
            delivery = inbox.get(POLL_S)
            outputs = closing_outputs(state)
            if delivery is None:
                outputs += overdue_eos(state)
            else:
                inbox.lossless = not getattr(delivery.msg, "realtime", not inbox.lossless)
                state.dropped = inbox.dropped
                try:
                    outputs += HANDLERS[type(delivery.msg)](state, delivery.msg, cfg)
                except (ValueError, RuntimeError):  # one bad frame must not end the stream
                    log.exception("message failed", extra={"stream": cfg.stream, "seq": delivery.msg.seq})
                log.debug("message handled", extra={"stream": cfg.stream, "seq": delivery.msg.seq,
                                                    "kind": delivery.msg.KIND, "queued": inbox.qsize(),
                                                    "seconds": round(time.monotonic() - now, 3)})
                next_credit = 0.0  # grant the next frame at once
            for replay in state.replays:
                for key, out in replay.due():  # kept already: published again, not recorded again
                    bus.publish(key, out)
            for key, out in outputs:
                bus.publish(key, out)
                for replay in state.replays:
                    replay.record(key, out)
            # served on after its end of stream while a consumer may still resume and need what was kept
            hold(bus, any(r.active and not r.finished for r in state.replays))
    finally:
        state.semantics.stop()
    return state


def answer_pca(state: FeaturesState, params: dict[str, str]) -> bytes:
    """The ``pca`` queryable's reply: the encoded ``PcaBasis`` of selector ``version=<n>``, or the latest one
    without a selector (called on a Zenoh thread: it only reads ``state``).

    Raises (the bus turns them into error replies):
        ValueError: the version is not an integer.
        LookupError: no basis yet, or none of that version was published in this run.
    """
    raw = params.get(VERSION_PARAM)
    if raw is None:
        if state.basis is None:
            raise LookupError("no PCA basis fitted yet")
        return pca_message(state.stream, state.basis).encode()
    try:
        version = int(raw)
    except ValueError:
        raise ValueError(f"{VERSION_PARAM} must be an integer, got {raw!r}") from None
    basis = state.bases.get(version)
    if basis is None:
        known = sorted(list(state.bases))  # list() first: the loop thread may add a version meanwhile
        have = f"versions {known[0]}..{known[-1]}" if known else "no basis yet"
        raise LookupError(f"PCA basis version {version} was not published in this run ({have})")
    return pca_message(state.stream, basis).encode()
