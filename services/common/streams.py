"""Serving every stream: one worker per stream a source announces, created on its first announcement, released
when its source is gone and it has been idle, each on its own thread so a stalled or slow stream never holds up
the others.

A service whose ``stream`` setting is :data:`keys.ALL_STREAMS` runs a :class:`StreamHost`; each worker is the
service's ordinary single-stream ``run(cfg, bus, stop)`` given a :class:`StreamScope` in place of the bus: the
scope declares the worker's subscriptions and queryables on the shared session and undeclares them when the worker
ends, and stamps its activity. Which streams this instance serves is decided by :mod:`services.common.sharding`
(replica ``i`` of ``N`` serves the streams whose rendezvous hash picks it).

Sessions: a source announces its stream with its session as the token's last segment
(``kmvipe/<stream>/@source/<session>``) and stamps every message with it. A worker serves one session of its
stream: its scope drops (and counts) messages of any other session and stamps what the worker publishes with its
own. When a new session appears on a stream (a publisher restarted), the host ends the old session's worker and
starts a fresh one, so a new session never lands in an earlier session's state or world frame. A worker run
outside a host (a service pinned to one stream) takes the session of the first message that has one.
"""
from __future__ import annotations

import dataclasses
import logging
import threading
import time
from dataclasses import dataclass, field
from typing import Callable, Iterable

from . import keys
from .bus import Bus, Delivery, Inbox
from .config_file import KmVipeSettings
from .schema import Credit, Eos, Message
from .sharding import ShardSettings, owns

from pydantic import Field
from pydantic_settings import SettingsConfigDict

log = logging.getLogger(__name__)

StreamWorker = Callable[[str, "StreamScope", threading.Event], object]


class StreamScope:
    """What one stream's worker sees of the bus: the same calls as :class:`Bus`, its declarations its own."""

    def __init__(self, bus: Bus, stream: str, session: str | None = None):
        self.bus, self.stream = bus, stream
        self.session = session  # None: taken from the first message that has one
        self._handles: list = []
        self.last_activity = time.monotonic()  # a message in, or one out that is not a heartbeat
        self.finished_at: float | None = None  # when the worker last sent its end of stream
        self.holding = False  # the worker still has work after its end of stream (features: a ba may resume)

    @property
    def instance(self) -> str:
        return self.bus.instance

    @property
    def service(self) -> str:
        return self.bus.service

    @property
    def stats(self):
        return self.bus.stats

    def _touch(self, on_message: Callable[[Delivery], None]) -> Callable[[Delivery], None]:
        def wrapped(delivery: Delivery) -> None:
            session = delivery.msg.session
            if session:
                if self.session is None:
                    self.session = session
                elif session != self.session:  # a late message of an ended session, or a stray one
                    self.bus.stats.record(delivery.key, "session",
                                          f"message of session {session} while serving session {self.session}")
                    return
            self.last_activity = time.monotonic()
            on_message(delivery)
        return wrapped

    def subscribe(self, key: str, on_message: Callable[[Delivery], None], expect: Iterable[type[Message]] = ()):
        handle = self.bus.subscribe(key, self._touch(on_message), expect)
        self._handles.append(handle)
        return handle

    def inbox(self, subscriptions: dict[str, Iterable[type[Message]]], maxsize: int = 1024, lossless: bool = True,
              droppable: tuple[type[Message], ...] = ()) -> Inbox:
        box = Inbox(maxsize, lossless, droppable)
        for key, kinds in subscriptions.items():
            self.subscribe(key, box.put, kinds)
        return box

    def hold(self, holding: bool) -> None:
        """Keep (True) or no longer keep this stream served after its end of stream, until ``idle_s``."""
        self.holding = holding

    def serve(self, key: str, handler):
        handle = self.bus.serve(key, handler)
        self._handles.append(handle)
        return handle

    def publish(self, key: str, msg: Message, *, drop_if_congested: bool = False) -> None:
        if self.session and msg.session != self.session:
            msg = dataclasses.replace(msg, session=self.session)
        if isinstance(msg, Eos):
            self.finished_at = time.monotonic()
        elif not isinstance(msg, Credit):  # credit and progress are heartbeats, not work
            self.last_activity = time.monotonic()
        self.bus.publish(key, msg, drop_if_congested=drop_if_congested)

    def request(self, selector: str, payload: bytes | None = None, timeout: float = 5.0, service: str = "") -> bytes:
        return self.bus.request(selector, payload, timeout, service)

    def ready(self) -> None:
        self.bus.ready()  # the instance's one token: it says the service is up, not which streams it serves

    def close(self) -> None:
        self.bus.release(self._handles)
        self._handles.clear()


@dataclass
class _Served:
    scope: StreamScope
    stop: threading.Event
    thread: threading.Thread
    sources: set[str] = field(default_factory=set)  # source tokens present for the stream
    gone_since: float | None = None  # when its last source went


class StreamHost:
    """Runs ``worker(stream, scope, stop)`` for every stream this instance owns, while it is wanted.

    A stream is wanted from its first source token until its sources are gone and the worker is done with it: it
    sent its end of stream and nothing came for ``linger_s`` since, or nothing happened at all for ``idle_s`` (a
    source that died without one). ``linger_s`` None keeps a finished stream (the mapstore: its map still answers
    queries) until a new stream needs its place. At most ``max_streams`` at once; a stream beyond that is refused (logged,
    counted in ``refused``) until one is released."""

    def __init__(self, bus: Bus, worker: StreamWorker, shard: ShardSettings | None = None, idle_s: float = 60.0,
                 max_streams: int = 16, linger_s: float | None = 2.0,
                 resume: Callable[[], Iterable[tuple[str, str]]] | None = None):
        """``resume``: the (stream, session) pairs this service has unfinished durable work for (ba's
        checkpoints); their workers start at once, with or without a source (it may have ended meanwhile)."""
        self.bus, self.worker, self.idle_s, self.max_streams = bus, worker, idle_s, max_streams
        self.resume = resume
        self.linger_s = linger_s
        self.shard = shard or ShardSettings()
        self.served: dict[str, _Served] = {}
        self.refused: set[str] = set()
        self.failed: dict[str, float] = {}  # stream -> when its worker last raised (restarted after failed_backoff_s)
        self.failed_backoff_s = 10.0
        self._lock = threading.Lock()
        self._wanted: dict[str, set[str]] = {}  # stream -> source keys present (fed by the Zenoh thread)
        self._newest: dict[str, str] = {}  # stream -> the session of the source token that appeared last

    def on_source(self, stream: str, key: str, present: bool) -> None:
        with self._lock:
            sources = self._wanted.setdefault(stream, set())
            (sources.add if present else sources.discard)(key)
            if present:
                self._newest[stream] = keys.parse_source_session(key)[1]

    def run(self, stop: threading.Event, poll_s: float = 0.1) -> None:
        """Serve until ``stop``; then stop every worker."""
        self.bus.watch_sources(self.on_source)
        self.bus.ready()
        for stream, session in (self.resume() if self.resume else ()):
            if stream not in self.served:
                log.info("resuming a stream's unfinished work", extra={"stream": stream, "session": session})
                self._start(stream, session)
                if stream in self.served:  # no source seen yet: released like a stream whose source went
                    self.served[stream].gone_since = time.monotonic()
        try:
            while not stop.wait(poll_s):
                self.step()
        finally:
            for stream in list(self.served):
                self._release(stream)

    def step(self) -> None:
        """Start workers for new owned streams and release the ones no longer wanted (one pass)."""
        now = time.monotonic()
        with self._lock:
            wanted = {s: set(keys_) for s, keys_ in self._wanted.items()}
            newest = dict(self._newest)
        for stream, sources in wanted.items():
            served = self.served.get(stream)
            session = newest.get(stream)
            if served is not None and sources and session and served.scope.session not in (None, session) \
                    and keys.source(stream, session) in sources:
                log.info("new session: the previous one ends", extra={
                    "stream": stream, "session": session, "previous_session": served.scope.session})
                self._release(stream)
                served = None
            if served is None and sources:
                self._start(stream, session)
            elif served is not None:
                served.gone_since = None if sources else (served.gone_since or now)
        for stream, served in list(self.served.items()):
            if not served.thread.is_alive() or (served.gone_since is not None and self._done(served, now)):
                self._release(stream)

    def _done(self, served: _Served, now: float) -> bool:
        scope = served.scope
        since = now - max(scope.last_activity, served.gone_since)
        if self.linger_s is None:
            return False  # kept until its place is needed (_make_room)
        return (self._finished(served) and since >= self.linger_s) or since >= self.idle_s

    @staticmethod
    def _finished(served: _Served) -> bool:
        scope = served.scope
        return not scope.holding and scope.finished_at is not None and scope.finished_at >= scope.last_activity

    def _make_room(self) -> bool:
        """Release the finished stream (its sources gone) that was quiet longest, if there is one."""
        done = [(served.scope.last_activity, stream) for stream, served in self.served.items()
                if served.gone_since is not None and (self._finished(served) or not served.thread.is_alive())]
        if not done:
            return False
        self._release(min(done)[1])
        return True

    def _start(self, stream: str, session: str | None = None) -> None:
        if not owns(stream, self.shard.index, self.shard.count):
            return
        if time.monotonic() - self.failed.get(stream, -1e9) < self.failed_backoff_s:
            return  # its worker just raised: not again at once (a traceback every poll helps nobody)
        if len(self.served) >= self.max_streams and not self._make_room():
            if stream not in self.refused:
                log.warning("stream refused: this instance serves its maximum", extra={
                    "stream": stream, "max_streams": self.max_streams})
                self.refused.add(stream)
            return
        self.refused.discard(stream)
        scope, stop = StreamScope(self.bus, stream, session), threading.Event()
        thread = threading.Thread(target=self._serve, args=(stream, scope, stop), name=f"stream-{stream}",
                                  daemon=True)
        self.served[stream] = _Served(scope, stop, thread)
        log.info("serving stream", extra={"stream": stream, "session": session, "streams": len(self.served)})
        thread.start()

    def _serve(self, stream: str, scope: StreamScope, stop: threading.Event) -> None:
        try:
            self.worker(stream, scope, stop)
        except Exception:  # one stream's failure is that stream's: logged, the others go on
            log.exception("stream worker failed", extra={"stream": stream})
            self.failed[stream] = time.monotonic()

    def _release(self, stream: str) -> None:
        served = self.served.pop(stream)
        served.stop.set()
        served.thread.join(timeout=30)
        served.scope.close()
        log.info("stream released", extra={"stream": stream, "streams": len(self.served)})


def session_of(bus) -> str | None:
    """The session a worker's bus serves (None: not known yet, or a plain :class:`Bus` outside any scope)."""
    return bus.session if isinstance(bus, StreamScope) else None


def hold(bus, holding: bool) -> None:
    """Keep a worker's stream served after its end of stream while ``holding`` (a no-op outside a host)."""
    if isinstance(bus, StreamScope):
        bus.hold(holding)


class HostSettings(KmVipeSettings):
    """How a service that serves every stream handles them (env prefix ``KMVIPE_STREAMS_``)."""

    model_config = SettingsConfigDict(env_prefix="KMVIPE_STREAMS_", env_file=".env", extra="ignore")

    idle_s: float = Field(60.0, gt=0)
    """A stream whose sources are gone is released after this long without a message (its state freed)."""
    max_streams: int = Field(16, ge=1)
    """Streams served at once by one instance; more are refused until one is released (add replicas instead)."""


def serve(stream: str, bus: Bus, stop: threading.Event, run_one: Callable[[str, object, threading.Event], object],
          host: HostSettings | None = None, keep_finished: bool = False,
          resume: Callable[[], Iterable[tuple[str, str]]] | None = None) -> None:
    """``run_one(stream, bus, stop)`` for one named stream, or, for :data:`keys.ALL_STREAMS`, a :class:`StreamHost`
    running it for every stream a source announces (each with a :class:`StreamScope` as its bus). With
    ``keep_finished`` a finished stream stays served until a new one needs its place."""
    if stream != keys.ALL_STREAMS:
        scope = StreamScope(bus, stream)
        try:
            run_one(stream, scope, stop)
        finally:
            scope.close()
        return
    host = host or HostSettings()
    StreamHost(bus, run_one, ShardSettings(), host.idle_s, host.max_streams,
               linger_s=None if keep_finished else 2.0, resume=resume).run(stop)
