"""The Zenoh bus every service uses: session from typed settings, typed publish/subscribe, queryables,
liveliness, and counting of bad payloads (a bad payload is logged once per kind and dropped — never a crash).
Every message in and out, bad payload, query and inbox drop is also counted in :mod:`services.common.metrics`.
"""
from __future__ import annotations

import json
import logging
import threading
import uuid
from collections import Counter, deque
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable

import zenoh

from . import keys, metrics
from .config import BusSettings
from .errors import BusError, ConfigError, DecodeError, ServiceTimeout
from .schema import Message, decode, encode

log = logging.getLogger(__name__)


def zenoh_config(settings: BusSettings) -> zenoh.Config:
    """Translate :class:`BusSettings` into a ``zenoh.Config``."""
    conf = zenoh.Config.from_file(str(settings.zenoh_config)) if settings.zenoh_config else zenoh.Config()
    conf.insert_json5("mode", json.dumps(settings.mode))
    if settings.listen:
        conf.insert_json5("listen/endpoints", json.dumps(settings.listen))
    if settings.connect:
        conf.insert_json5("connect/endpoints", json.dumps(settings.connect))
    conf.insert_json5("scouting/multicast/enabled", json.dumps(settings.multicast_scouting))
    conf.insert_json5("transport/shared_memory/enabled", json.dumps(settings.shared_memory))
    if settings.shared_memory:  # the pool is made at session start, so the first frames use it too
        conf.insert_json5("transport/shared_memory/mode", json.dumps("init"))
        conf.insert_json5("transport/shared_memory/transport_optimization/pool_size",
                          json.dumps(settings.shm_pool_mib << 20))
    if settings.tls_root_ca:
        conf.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(str(_readable(settings.tls_root_ca))))
    if settings.user:
        conf.insert_json5("transport/auth/usrpwd/user", json.dumps(settings.user))
        conf.insert_json5("transport/auth/usrpwd/password", json.dumps(bus_password(settings)))
    return conf


def bus_password(settings: BusSettings) -> str:
    """The password of ``settings.user``, from the setting or its file."""
    if settings.password is not None:
        return settings.password.get_secret_value()
    return _readable(settings.password_file).read_text().rstrip("\r\n")


def _readable(path: Path) -> Path:
    # Zenoh reports a missing file only as "unable to connect"; name it here instead
    if not path.is_file():
        raise ConfigError(f"bus secret file {path} does not exist (KMVIPE_BUS_PASSWORD_FILE / KMVIPE_BUS_TLS_ROOT_CA; "
                          "docs/SECURITY.md says how to make them)")
    return path


def open_session(settings: BusSettings) -> zenoh.Session:
    try:
        return zenoh.open(zenoh_config(settings))
    except zenoh.ZError as exc:
        raise BusError(
            f"cannot open the Zenoh session (mode {settings.mode}, listen {settings.listen}, connect "
            f"{settings.connect}, user {settings.user or 'none'}): {exc}. Check that a router runs at the connect "
            "endpoint and that listen endpoints are free (KMVIPE_BUS_CONNECT / KMVIPE_BUS_LISTEN); a secured router "
            "also refuses a missing or wrong credential (KMVIPE_BUS_USER, KMVIPE_BUS_PASSWORD_FILE) and a tls/ "
            "endpoint needs the CA that signed it (KMVIPE_BUS_TLS_ROOT_CA; docs/SECURITY.md)."
        ) from exc


class PayloadStats:
    """Counts payloads that failed to decode or to be handled, per key and reason; logs each reason once."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.counts: Counter[tuple[str, str]] = Counter()

    def record(self, key: str, reason: str, detail: str) -> None:
        with self._lock:
            first = (key, reason) not in self.counts
            self.counts[(key, reason)] += 1
        metrics.count_bad_payload(key, reason)
        if first:
            log.warning("dropped bad payload (logged once per kind)", extra={"key": key, "reason": reason, "detail": detail})

    @property
    def total(self) -> int:
        with self._lock:
            return sum(self.counts.values())


@dataclass(frozen=True)
class Delivery:
    """A decoded message and the key it arrived on."""

    key: str
    msg: Message


class Inbox:
    """A bounded queue of deliveries for a service's loop, with the drop policy of the pacing mode.

    ``lossless``: never drops; credit keeps it below ``maxsize``, and should it fill anyway it grows (counted in
    ``overflowed``) rather than lose what upstream was promised. Real-time: when full, the oldest queued message
    of a ``droppable`` kind (frames, never keyframes, codes, bases or EOS) makes room; if none is queued, an
    incoming droppable message is dropped and an essential one is still queued. Drops are counted per kind, and
    ``on_drop`` (if given) is told of each.
    """

    def __init__(self, maxsize: int, lossless: bool = False, droppable: tuple[type, ...] = (),
                 on_drop: Callable[[Delivery], None] | None = None):
        self.maxsize, self.lossless, self.droppable, self.on_drop = maxsize, lossless, droppable, on_drop
        self._items: deque[Delivery] = deque()
        self._ready = threading.Condition()
        self.dropped_by_kind: Counter[str] = Counter()
        self.overflowed = 0
        self._widened = 0  # a bound above maxsize until the queue drains back to maxsize (:meth:`widen`)
        self.last_key: str | None = None  # the stream its depth is reported under (metrics)
        metrics.INBOXES.track(self)

    @property
    def dropped(self) -> int:
        return sum(self.dropped_by_kind.values())

    @property
    def bound(self) -> int:
        """How many messages it holds before the drop policy applies now."""
        return max(self.maxsize, self._widened)

    def widen(self, maxsize: int) -> None:
        """Hold up to ``maxsize`` until the queue next drains to its own bound: its consumer is not up yet, and what
        comes meanwhile is early, not stale."""
        with self._ready:
            self._widened = maxsize

    def put(self, item: Delivery) -> None:
        with self._ready:
            self.last_key = item.key
            if len(self._items) >= self.bound:
                victim = self._make_room(item)
                if victim is item:
                    return
            self._items.append(item)
            self._ready.notify()

    def _make_room(self, item: Delivery) -> Delivery | None:
        """The delivery dropped to take ``item`` (``item`` itself when it is the one to go), or None."""
        if self.lossless or not self.droppable:
            self.overflowed += 1
            metrics.count_inbox_overflow(item.key)
            if self.overflowed == 1 or not self.droppable:
                log.warning("inbox over its bound; kept", extra={"key": item.key, "seq": item.msg.seq})
            return None
        victim = next((d for d in self._items if isinstance(d.msg, self.droppable)), None)
        if victim is not None:
            self._items.remove(victim)
        elif isinstance(item.msg, self.droppable):
            victim = item
        else:
            self.overflowed += 1
            metrics.count_inbox_overflow(item.key)
            return None
        self.dropped_by_kind[victim.msg.KIND] += 1
        metrics.count_inbox_drop(victim.key, victim.msg.KIND)
        log.info("inbox full: dropped the oldest frame", extra={"key": victim.key, "seq": victim.msg.seq})
        if self.on_drop is not None:  # called with the inbox locked: it must only take note
            self.on_drop(victim)
        return victim

    def get(self, timeout: float) -> Delivery | None:
        with self._ready:
            if not self._items and not self._ready.wait_for(lambda: bool(self._items), timeout):
                return None
            item = self._items.popleft()
            if len(self._items) <= self.maxsize:  # drained back to its own bound: a widening ends
                self._widened = 0
            return item

    def qsize(self) -> int:
        with self._ready:
            return len(self._items)

    def count(self, kind: type) -> int:
        """Queued messages of ``kind``."""
        with self._ready:
            return sum(isinstance(d.msg, kind) for d in self._items)


class Bus:
    """One service instance on the bus: a Zenoh session plus its liveliness token."""

    def __init__(self, settings: BusSettings, service: str, instance: str | None = None):
        self.service = keys.check_name(service, "service")
        self.instance = keys.check_name(instance or uuid.uuid4().hex[:8], "instance")
        self.session = open_session(settings)
        self.stats = PayloadStats()
        self._publishers: dict[tuple[str, bool], zenoh.Publisher] = {}
        self._publish_lock = threading.Lock()
        self._handles: list = []
        self._token = None
        self._stage_clock = metrics.StageClock()

    @property
    def is_open(self) -> bool:
        """Whether the Zenoh session is open (``/livez``)."""
        return not self.session.is_closed()

    @property
    def is_ready(self) -> bool:
        """Whether :meth:`ready` declared the liveliness token (``/readyz``)."""
        return self._token is not None

    def ready(self) -> None:
        """Declare this instance's liveliness token. Services call it once their subscriptions are declared, so
        "alive" on the bus means "ready to take messages" (the runner starts the source only then)."""
        if self._token is None:
            self._token = self.session.liveliness().declare_token(keys.alive(self.service, self.instance))

    # --- publish / subscribe -------------------------------------------------------------------------
    def publish(self, key: str, msg: Message, *, drop_if_congested: bool = False) -> None:
        """Send ``msg`` reliably on ``key``. By default a congested link blocks (lossless); with
        ``drop_if_congested`` the message is dropped instead (real-time streams)."""
        self.put(key, encode(msg), drop_if_congested=drop_if_congested)
        self._stage_clock.published(key, msg.seq)

    def put(self, key: str, payload: bytes, *, drop_if_congested: bool = False) -> None:
        with self._publish_lock:  # services publish from more than one thread (ba: tracking and mapping)
            pub = self._publishers.get((key, drop_if_congested))
            if pub is None:
                congestion = zenoh.CongestionControl.DROP if drop_if_congested else zenoh.CongestionControl.BLOCK
                pub = self.session.declare_publisher(key, congestion_control=congestion,
                                                     reliability=zenoh.Reliability.RELIABLE)
                self._publishers[(key, drop_if_congested)] = pub
        pub.put(payload)
        metrics.count_message(metrics.OUT, key, len(payload))  # handed to Zenoh (a congested DROP link may lose it)

    def subscribe(self, key: str, on_message: Callable[[Delivery], None], expect: Iterable[type[Message]] = ()):
        """Call ``on_message`` (on a Zenoh thread) for every valid message on ``key``; bad payloads are counted.
        Returns the subscriber (undeclared by :meth:`close`, or earlier by :meth:`release`)."""
        allowed = tuple(expect)

        def _callback(sample: zenoh.Sample) -> None:
            key_str = str(sample.key_expr)
            payload = sample.payload.to_bytes()
            try:
                msg = decode(payload)
                if allowed and not isinstance(msg, allowed):
                    raise DecodeError(f"unexpected message kind {msg.KIND!r} on {key_str}")
            except DecodeError as exc:
                self.stats.record(key_str, "decode", str(exc))
                return
            metrics.count_message(metrics.IN, key_str, len(payload))
            self._stage_clock.arrived(key_str, msg.seq)
            try:
                on_message(Delivery(key_str, msg))
            except Exception as exc:  # the error boundary of a callback: log, count, keep the session alive
                log.exception("handler failed", extra={"key": key_str, "seq": msg.seq})
                self.stats.record(key_str, "handler", repr(exc))

        handle = self.session.declare_subscriber(key, _callback)
        self._handles.append(handle)
        return handle

    def inbox(self, subscriptions: dict[str, Iterable[type[Message]]], maxsize: int = 1024, lossless: bool = True,
              droppable: tuple[type[Message], ...] = ()) -> Inbox:
        """Subscribe to several keys (each with the message kinds it may carry) into one bounded inbox (see
        :class:`Inbox` for what happens when it is full)."""
        box = Inbox(maxsize, lossless, droppable)
        for key, kinds in subscriptions.items():
            self.subscribe(key, box.put, kinds)
        return box

    # --- queries -------------------------------------------------------------------------------------
    def serve(self, key: str, handler: Callable[[str, dict, bytes | None], bytes]):
        """Declare a queryable; ``handler(key, parameters, payload) -> reply bytes``. Errors become error
        replies with their message, never a crash."""

        def _callback(query: zenoh.Query) -> None:
            metrics.count_query(str(query.key_expr))
            payload = query.payload.to_bytes() if query.payload is not None else None
            try:
                params = dict(query.selector.parameters)
                query.reply(query.key_expr, handler(str(query.key_expr), params, payload))
            except Exception as exc:
                self.stats.record(str(query.key_expr), "query", repr(exc))
                query.reply_err(f"{type(exc).__name__}: {exc}")

        handle = self.session.declare_queryable(key, _callback)
        self._handles.append(handle)
        return handle

    def release(self, handles: Iterable) -> None:
        """Undeclare subscribers and queryables before :meth:`close` (a stream a service stopped serving)."""
        for handle in handles:
            if handle in self._handles:
                self._handles.remove(handle)
                handle.undeclare()

    # --- sources -------------------------------------------------------------------------------------
    def announce(self, stream: str, session: str | None = None):
        """Declare that this instance streams ``stream`` in ``session`` (default: the instance id), so services
        serving every stream start a worker for it; returns the token, which the caller undeclares when the
        stream ends."""
        return self.session.liveliness().declare_token(keys.source(stream, session or self.instance))

    def watch_sources(self, on_change: Callable[[str, str, bool], None]) -> None:
        """``on_change(stream, source key, present)`` for every source token there is and every one that appears
        or goes (a Zenoh thread; tokens declared before this call are reported too)."""

        def _callback(sample: zenoh.Sample) -> None:
            key = str(sample.key_expr)
            try:
                stream = keys.parse_source(key)
            except (ValueError, ConfigError) as exc:  # a foreign token on our keys: counted, ignored
                self.stats.record(key, "source", str(exc))
                return
            on_change(stream, key, sample.kind == zenoh.SampleKind.PUT)

        self._handles.append(self.session.liveliness().declare_subscriber(keys.source(), _callback, history=True))

    def request(self, selector: str, payload: bytes | None = None, timeout: float = 5.0, service: str = "") -> bytes:
        """Ask one queryable; the first OK reply's bytes. Raises ServiceTimeout, or RuntimeError for an error reply."""
        errors = []
        for reply in self.session.get(selector, payload=payload, timeout=timeout):
            if reply.ok is not None:
                return reply.ok.payload.to_bytes()
            errors.append(reply.err.payload.to_string())
        if errors:
            raise RuntimeError(f"{service or selector}: {errors[0]}")
        raise ServiceTimeout(service or selector, timeout)

    # --- liveliness ----------------------------------------------------------------------------------
    def alive(self, timeout: float = 1.0) -> dict[str, list[str]]:
        """Services currently alive on the bus: ``{service: [instance, ...]}``."""
        found: dict[str, list[str]] = {}
        for reply in self.session.liveliness().get(keys.alive("*", "*"), timeout=timeout):
            if reply.ok is not None:
                service, instance = keys.parse_alive(str(reply.ok.key_expr))
                found.setdefault(service, []).append(instance)
        return found

    def close(self) -> None:
        for handle in self._handles:
            handle.undeclare()
        self._handles.clear()
        if self._token is not None:
            self._token.undeclare()
            self._token = None
        self.session.close()

    def __enter__(self) -> "Bus":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
