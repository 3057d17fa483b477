"""Features service: ``frame`` in; ``keyframe`` / ``frame_lite`` / ``pca`` / ``eos`` out; ``credit`` back to
ingest; ``intrinsics`` from ba refine the focal-length guess. One handler per message kind; ``run`` only
receives, handles and publishes.

The ``pca`` key is also a queryable over every basis version published in this run (``?version=<n>``; the
latest without a selector), so a consumer that missed one (late join, restart, lost message) can fetch it."""
from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field

import cv2
import numpy as np
import torch

from ..common import keys
from ..common.bus import Bus
from ..common.models.backbones import normalise_rgb
from ..common.device import resolve_device
from ..common.models.loaders import load_backbone, load_depth_model
from ..common.models.store import ModelStore
from ..common.schema import Credit, Eos, Frame, FrameLite, Intrinsics, Keyframe, Message, PcaBasis
from .config import FeaturesSettings
from .core.geometry import Intrinsics as K4
from .core.pca import PcaBasis as CoreBasis
from .core.pipeline import CodeQueue, FeaturesCore, KeyframeOut, LiteOut
from .oracle import ORACLE_BACKBONE, SynthOracleBackbone

log = logging.getLogger(__name__)
POLL_S = 0.05
CREDIT_PERIOD_S = 0.1
VERSION_PARAM = "version"  # selector parameter of the pca queryable: kmvipe/<s>/pca?version=<n>

Outputs = list[tuple[str, Message]]


@dataclass
class FeaturesState:
    core: FeaturesCore
    codes: CodeQueue
    stream: str
    last_seq: int = -1  # highest frame seq handled (credit is granted beyond it)
    last_keyframe_seq: int = -1
    last_frame: tuple[int, int, int] = (0, 0, 0)  # original (width, height, t_ns) of the latest frame
    frames_seen: int = 0
    pending_eos: Eos | None = None  # ingest's EOS, held until every frame it announced has arrived
    eos_deadline: float = 0.0
    basis: CoreBasis | None = None  # the latest basis
    # every basis published in this run, by version, for the pca queryable (K x D float32: ~100 KB at K = 32,
    # D = 768, so ~5 MB for the ~50 versions of a KITTI drive)
    bases: dict[int, CoreBasis] = field(default_factory=dict)
    published: int = 0
    bad_frames: int = 0
    # keyframe seq -> (original width, height, t_ns): keyframes may wait for the PCA basis, so what leaves later
    # must carry its own size and time, not those of the frame that released it
    pending: dict[int, tuple[int, int, int]] = field(default_factory=dict)


def build_state(cfg: FeaturesSettings) -> FeaturesState:
    """Load the models named in the settings (one clear ModelError if one is missing)."""
    torch.set_num_threads(cfg.threads)
    store = ModelStore(cfg.models_dir)
    if cfg.backbone == ORACLE_BACKBONE:  # test double: exact synthetic-world labels instead of a model
        backbone = SynthOracleBackbone(cfg.oracle_params())
    else:
        backbone = load_backbone(cfg.backbone, store, cfg.device, cfg.runtime, cfg.threads, cfg.half)
    depth = load_depth_model(cfg.depth_model, store, cfg.device, cfg.half) if cfg.depth_model else None
    device = resolve_device(cfg.device)
    core = FeaturesCore(cfg.params(getattr(backbone, "patch_size", 14), device.type == "cuda"), backbone,
                        lambda image: normalise_rgb(image, device), depth)
    return FeaturesState(core, CodeQueue(core.params.pca, backbone.output_space), cfg.stream)


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
    if state.pending_eos is not None and state.frames_seen >= state.pending_eos.count:
        outputs += _finish(state, state.pending_eos)
    return outputs


def _frame(state: FeaturesState, msg: Frame, cfg: FeaturesSettings) -> Outputs:
    state.last_seq = max(state.last_seq, msg.seq)
    state.last_frame = (msg.width, msg.height, msg.t_ns)
    try:
        image = decode_image(msg)
    except ValueError as exc:
        state.bad_frames += 1
        log.warning("corrupt frame skipped", extra={"stream": msg.stream, "seq": msg.seq, "error": str(exc)})
        return []
    hint = K4(*map(float, msg.intrinsics)) if msg.intrinsics is not None else None
    _announce_frame(state, msg.seq)
    out = state.core.process(msg.seq, image, hint, None if msg.depth is None else np.asarray(msg.depth))
    if isinstance(out, LiteOut):
        lite = FrameLite(msg.stream, msg.seq, msg.t_ns, image=out.grey, intrinsics=np.array(out.intrinsics, np.float64),
                         ref_seq=state.last_keyframe_seq)
        return [(keys.topic(msg.stream, keys.FRAME_LITE), lite)]
    state.last_keyframe_seq = out.seq
    state.pending[out.seq] = (msg.width, msg.height, msg.t_ns)
    return _coded(state, msg.stream, *state.codes.add(out))


def _announce_frame(state: FeaturesState, seq: int) -> None:
    """Tell a frame-aware backbone (the synthetic oracle) which frame it is about to see."""
    set_frame = getattr(state.core.backbone, "set_frame", None)
    if set_frame is not None:
        set_frame(seq)


def handle_intrinsics(state: FeaturesState, msg: Intrinsics, cfg: FeaturesSettings) -> Outputs:
    state.core.intrinsics.refine(K4(*map(float, msg.intrinsics)), msg.width, msg.height)
    return []


def handle_eos(state: FeaturesState, msg: Eos, cfg: FeaturesSettings) -> Outputs:
    """Ingest ended: finish once every frame it sent has arrived (see ``eos_wait_s``)."""
    if msg.stage != "ingest":
        return []
    if state.frames_seen >= msg.count:
        return _finish(state, msg)
    state.pending_eos, state.eos_deadline = msg, time.monotonic() + cfg.eos_wait_s
    return []


def overdue_eos(state: FeaturesState) -> Outputs:
    """Finish a held EOS whose frames did not all come within ``eos_wait_s`` (some were lost upstream)."""
    if state.pending_eos is None or time.monotonic() < state.eos_deadline:
        return []
    log.warning("end of stream with frames missing", extra={"stream": state.stream, "seen": state.frames_seen,
                                                           "announced": state.pending_eos.count})
    return _finish(state, state.pending_eos)


def _finish(state: FeaturesState, msg: Eos) -> Outputs:
    """The last frame becomes a keyframe, pending keyframes are coded, and the EOS goes on."""
    state.pending_eos = None
    outputs: Outputs = []
    if state.core.last_lite is not None:
        _announce_frame(state, state.core.last_lite[1])
    last = state.core.promote_last()
    if last is not None:
        state.pending[last.seq] = state.last_frame
        outputs += _coded(state, msg.stream, *state.codes.add(last))
    outputs += _coded(state, msg.stream, *state.codes.flush())
    eos = Eos(msg.stream, msg.seq, time.time_ns(), stage="features", count=state.published, reason=msg.reason)
    state.frames_seen = 0  # a new stream may follow on the same key
    return outputs + [(keys.topic(msg.stream, keys.EOS), eos)]


def _coded(state: FeaturesState, stream: str, basis: CoreBasis | None,
           ready: list[tuple[KeyframeOut, np.ndarray]]) -> Outputs:
    outputs: Outputs = []
    if basis is not None:
        state.basis = basis
        state.bases[basis.version] = basis
        outputs.append((keys.topic(stream, keys.PCA), pca_message(stream, basis, ready[0][0].seq if ready else 0)))
    for kf, codes in ready:
        w, h, t_ns = state.pending.pop(kf.seq)
        disparity = None if kf.disparity is None else kf.disparity.astype(np.float32)
        outputs.append((keys.topic(stream, keys.KEYFRAME), Keyframe(
            stream, kf.seq, t_ns, image=kf.image, intrinsics=np.array(kf.intrinsics, np.float64), orig_width=w,
            orig_height=h, pca_version=state.basis.version, codes=codes, disparity_prior=disparity)))
        state.published += 1
        log.debug("keyframe", extra={"stream": stream, "seq": kf.seq, **{k: round(v, 3) for k, v in kf.seconds.items()}})
    return outputs


def pca_message(stream: str, basis: CoreBasis, seq: int = 0) -> PcaBasis:
    return PcaBasis(stream, seq, time.time_ns(), version=basis.version, backbone=basis.backbone,
                    mean=basis.mean.astype(np.float32), components=basis.components.astype(np.float32),
                    explained_variance=basis.explained_variance.astype(np.float32))


HANDLERS = {Frame: handle_frame, Intrinsics: handle_intrinsics, Eos: handle_eos}


def run(cfg: FeaturesSettings, bus: Bus, stop: threading.Event, state: FeaturesState | None = None) -> FeaturesState:
    state = state or build_state(cfg)
    topic = lambda name: keys.topic(cfg.stream, name)  # noqa: E731
    inbox = bus.inbox({topic(keys.FRAME): [Frame], topic(keys.INTRINSICS): [Intrinsics], topic(keys.EOS): [Eos]},
                      maxsize=4 * cfg.credit_window + 16)
    # late joiners (a restarted mapstore) ask for the current basis, consumers that missed one for its version
    bus.serve(topic(keys.PCA), lambda key, params, payload: answer_pca(state, params))
    bus.ready()
    log.info("features ready", extra={"stream": cfg.stream, "backbone": cfg.backbone})
    next_credit = 0.0
    while not stop.is_set():
        if time.monotonic() >= next_credit:  # credit doubles as a heartbeat, so ingest knows we are alive
            bus.publish(topic(keys.CREDIT), Credit(cfg.stream, state.last_seq + cfg.credit_window, time.time_ns(),
                                                   consumer=f"features-{bus.instance}"))
            next_credit = time.monotonic() + CREDIT_PERIOD_S
        delivery = inbox.get(POLL_S)
        if delivery is None:
            for key, out in overdue_eos(state):
                bus.publish(key, out)
            continue
        try:
            outputs = HANDLERS[type(delivery.msg)](state, delivery.msg, cfg)
        except (ValueError, RuntimeError) as exc:  # one bad frame must not end the stream
            log.exception("message failed", extra={"stream": cfg.stream, "seq": delivery.msg.seq})
            outputs = []
        for key, out in outputs:
            bus.publish(key, out)
        next_credit = 0.0  # grant the next frame at once
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
