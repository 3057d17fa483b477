"""Ingest service: reads a source, publishes ``frame`` messages under credit-based flow control, ends with
``eos``. Corrupt frames are logged and counted; the stream goes on."""
from __future__ import annotations

import logging
import threading
import time

import cv2
import numpy as np

from ..common import keys
from ..common.bus import Bus, Delivery
from ..common.schema import Credit, Eos, Frame
from .config import IngestSettings
from .core.pacing import CreditLedger, Decision, IngestCounters, decide
from .resend import ResendBuffer
from .sources import BadFrame, Source, SourceFrame, open_source

log = logging.getLogger(__name__)
CREDIT_POLL_S = 0.05


def frame_message(cfg: IngestSettings, seq: int, item: SourceFrame, session: str = "",
                  features_handled: int = -1) -> Frame:
    """The wire message of one source frame (JPEG or raw RGB); ``features_handled``: see :class:`Frame`."""
    h, w = item.rgb.shape[:2]
    intrinsics = np.asarray(cfg.intrinsics, np.float64) if cfg.intrinsics else None
    depth = item.depth if cfg.use_depth else None
    realtime = cfg.pacing == "realtime"
    if cfg.encoding == "jpeg":
        ok, buf = cv2.imencode(".jpg", cv2.cvtColor(item.rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, cfg.jpeg_quality])
        if not ok:
            raise ValueError("JPEG encoding failed")
        return Frame(cfg.stream, seq, item.t_ns, w, h, jpeg=buf.tobytes(), intrinsics=intrinsics, depth=depth,
                     realtime=realtime, session=session, features_handled=features_handled)
    return Frame(cfg.stream, seq, item.t_ns, w, h, image=item.rgb, intrinsics=intrinsics, depth=depth, realtime=realtime,
                 session=session, features_handled=features_handled)


class CreditGate:
    """Thread-safe credit state fed by the ``credit`` subscription (Zenoh thread), read by the send loop. Credit
    stamped with another session (a consumer still serving this stream's previous source) is not ours."""

    def __init__(self, ttl_s: float, session: str = ""):
        self.session = session
        self.resend = ResendBuffer()  # lossless: what features has not handled, for a features that restarts
        self.features_ended = threading.Event()
        self._ledger = CreditLedger(ttl_s)
        self._cond = threading.Condition()
        self.ever_granted = False

    def on_credit(self, delivery: Delivery) -> None:
        msg = delivery.msg
        assert isinstance(msg, Credit)
        if msg.session and self.session and msg.session != self.session:
            return
        self.resend.on_credit(msg)
        with self._cond:
            self._ledger.grant(msg.consumer or "anonymous", msg.seq, time.monotonic())
            self.ever_granted = True
            self._cond.notify_all()

    def on_eos(self, delivery: Delivery) -> None:
        msg = delivery.msg
        if msg.stage == "features" and (not msg.session or msg.session == self.session):
            self.features_ended.set()

    def limit(self) -> int:
        with self._cond:
            return self._ledger.limit(time.monotonic())

    def wait_for(self, seq: int, timeout: float) -> bool:
        with self._cond:
            return self._cond.wait_for(lambda: self._ledger.limit(time.monotonic()) >= seq, timeout)


def run(cfg: IngestSettings, bus: Bus, stop: threading.Event, source: Source | None = None) -> IngestCounters:
    """Stream ``cfg.source`` (or ``source``) onto the bus until it ends or ``stop`` is set."""
    source = source or open_source(cfg.source, fps=cfg.fps, use_depth=cfg.use_depth,
                                   depth_scale=cfg.depth_scale, topic=cfg.topic)
    session = keys.new_session()  # a restarted source is a new session: never fused into the last one's world
    gate = CreditGate(cfg.credit_ttl_s, session)
    bus.subscribe(keys.topic(cfg.stream, keys.CREDIT), gate.on_credit, expect=[Credit])
    bus.subscribe(keys.topic(cfg.stream, keys.EOS), gate.on_eos, expect=[Eos])
    bus.ready()
    token = bus.announce(cfg.stream, session)  # services that serve every stream start this session's workers on it
    try:
        return _stream(cfg, bus, stop, source, gate)
    finally:
        token.undeclare()


def _stream(cfg: IngestSettings, bus: Bus, stop: threading.Event, source: Source, gate: CreditGate) -> IngestCounters:
    if not _await_first_consumer(gate, cfg.wait_for_consumer_s, stop):
        # lossless gives up with a clear error below; realtime plays on and drops what nobody takes
        log.warning("no consumer has granted credit yet", extra={"stream": cfg.stream, "waited_s": cfg.wait_for_consumer_s})
    frame_key = keys.topic(cfg.stream, keys.FRAME)
    counters, seq, reason = IngestCounters(), -1, "end"
    lossless = cfg.pacing == "lossless"
    pace_fps = cfg.fps or source.fps
    started = time.monotonic()
    log.info("streaming", extra={"stream": cfg.stream, "session": gate.session, "source": source.name,
                                 "pacing": cfg.pacing})

    for position, item in enumerate(source.frames()):
        if stop.is_set():
            reason = "stopped"
            break
        if position % cfg.stride:
            continue
        if isinstance(item, BadFrame):
            counters.corrupt += 1
            log.warning("skipped unreadable frame", extra={"stream": cfg.stream, "index": item.index, "reason": item.reason})
            continue
        counters.read += 1
        seq += 1
        if not lossless and not source.live and pace_fps:
            # keep the recording's pace: realtime means the consumer sees the video as if live
            delay = started + counters.read / pace_fps - time.monotonic()
            if delay > 0:
                stop.wait(delay)
        if not _await_credit(bus, gate, seq, lossless, cfg, stop):
            reason = "stopped" if stop.is_set() else "error"
            break
        if decide(seq, gate.limit(), lossless) is Decision.DROP:
            counters.dropped += 1
            continue
        try:
            frame = frame_message(cfg, seq, item, gate.session, gate.resend.durable)
            bus.publish(frame_key, frame, drop_if_congested=not lossless)
            if lossless:
                gate.resend.record(frame)
        except ValueError as exc:
            counters.corrupt += 1
            log.warning("could not encode frame", extra={"stream": cfg.stream, "seq": seq, "error": str(exc)})
            continue
        counters.sent += 1
        if cfg.max_frames and counters.sent >= cfg.max_frames:
            break

    eos = Eos(cfg.stream, seq, time.time_ns(), stage="ingest", count=counters.sent, reason=reason,
              dropped=counters.dropped, session=gate.session)
    bus.publish(keys.topic(cfg.stream, keys.EOS), eos)
    log.info("end of stream", extra={"stream": cfg.stream, "reason": reason, **counters.__dict__})
    if lossless and reason == "end":
        gate.resend.record(eos)
        _hold_until_taken(cfg, bus, stop, gate)
    return counters


def _hold_until_taken(cfg: IngestSettings, bus: Bus, stop: threading.Event, gate: CreditGate) -> None:
    """Lossless: stay announced until features has ended the stream too (or ``hold_after_end_s``), sending again
    what a features that restarted meanwhile has not handled."""
    deadline = time.monotonic() + cfg.hold_after_end_s
    while not stop.is_set() and not gate.features_ended.is_set() and time.monotonic() < deadline:
        _resend(bus, cfg, gate)
        gate.features_ended.wait(CREDIT_POLL_S)


def _resend(bus: Bus, cfg: IngestSettings, gate: CreditGate) -> None:
    again = gate.resend.due()
    if again:
        log.info("features restarted: sending again what it had not handled", extra={
            "stream": cfg.stream, "from_seq": again[0].seq, "messages": len(again)})
    for msg in again:
        bus.publish(keys.topic(cfg.stream, keys.FRAME if isinstance(msg, Frame) else keys.EOS), msg)


def _await_first_consumer(gate: CreditGate, timeout_s: float, stop: threading.Event) -> bool:
    """Wait up to ``timeout_s`` for any credit, returning early on ``stop`` (docker stop must not wait a minute)."""
    deadline = time.monotonic() + timeout_s
    while not stop.is_set():
        if gate.wait_for(0, min(CREDIT_POLL_S, max(0.0, deadline - time.monotonic()))):
            return True
        if time.monotonic() >= deadline:
            return False
    return False


def _await_credit(bus: Bus, gate: CreditGate, seq: int, lossless: bool, cfg: IngestSettings,
                  stop: threading.Event) -> bool:
    """Lossless: block until credit covers ``seq`` (False if stopped or no consumer ever appeared)."""
    if not lossless:
        return True
    waited = 0.0
    while not gate.wait_for(seq, CREDIT_POLL_S):
        if stop.is_set():
            return False
        _resend(bus, cfg, gate)  # a features that restarted waits for the frames it lost
        waited += CREDIT_POLL_S
        if not gate.ever_granted and waited > cfg.wait_for_consumer_s:
            log.error(
                "no consumer granted credit; is the features service running on this bus? "
                "(use --pacing realtime to publish without one)",
                extra={"stream": cfg.stream, "waited_s": round(waited, 1)},
            )
            return False
    return True
