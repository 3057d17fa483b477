"""Prometheus metrics of a service process and its health endpoints.

The bus (:mod:`services.common.bus`) counts into the process's default registry, where prometheus_client's own
collectors already report the process's resident memory and CPU (``process_resident_memory_bytes``,
``process_cpu_seconds_total``, Linux). Series are labelled by ``stream`` and ``topic`` (the key
``kmvipe/<stream>/<topic>``), never by the full key, so their number stays bounded:

=======================================================  =====================================================
``kmvipe_bus_messages_total{direction,stream,topic}``    messages received (decoded) and published
``kmvipe_bus_bytes_total{direction,stream,topic}``       their payload bytes
``kmvipe_bus_bad_payloads_total{stream,topic,reason}``   payloads dropped (``decode``, ``handler``, ``query``,
                                                         ``source``; :class:`bus.PayloadStats`)
``kmvipe_bus_queries_total{stream,topic}``               queries answered by this process's queryables
``kmvipe_inbox_depth{stream}``                           messages waiting in the service's inboxes
``kmvipe_inbox_dropped_total{stream,kind}``              messages a real-time inbox dropped
``kmvipe_inbox_overflowed_total{stream}``                messages a full lossless inbox kept past its bound
``kmvipe_stage_latency_seconds{stream,topic}``           a frame's time in this stage (:class:`StageClock`)
``kmvipe_process_peak_rss_bytes``                        peak resident memory (``ru_maxrss``)
``kmvipe_ready``, ``kmvipe_service_info``                1 once the service declared itself ready; who it is
=======================================================  =====================================================

:class:`HealthServer` serves them on ``/metrics`` with ``/livez`` (the process and its bus session are up) and
``/readyz`` (the service declared itself ready with ``Bus.ready()``), started by ``service_main`` when
``KMVIPE_METRICS_PORT`` is set (docs/DEPLOY.md, "Metrics and health").
"""
from __future__ import annotations

import contextlib
import logging
import re
import resource
import socketserver
import threading
import time
import weakref
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Iterator, Protocol

from prometheus_client import REGISTRY, CollectorRegistry, Counter, Histogram
from prometheus_client.core import GaugeMetricFamily
from prometheus_client.exposition import CONTENT_TYPE_LATEST, generate_latest

from . import keys
from .config import MetricsSettings
from .errors import ConfigError

log = logging.getLogger(__name__)

IN, OUT = "in", "out"
OTHER = "other"
"""The topic label of a key outside ``kmvipe/<stream>/<topic>`` (and the stream label of an invalid stream)."""
MAX_CACHED_KEYS = 4096
"""Keys whose label children are cached; past it they are looked up on every message (slower, still right)."""
STAGE_INPUTS = frozenset((keys.FRAME, keys.FRAME_LITE, keys.KEYFRAME))
"""Topics whose arrival starts a frame's stage clock."""
NOT_STAGE_OUTPUTS = frozenset((keys.CREDIT, keys.EOS))
"""Topics that never stop it: credit is a heartbeat ahead of the frames, EOS is about the stream."""
LATENCY_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0)

_KNOWN_TOPICS = frozenset(keys.TOPICS) | {keys.SOURCE}
_STREAM = re.compile(r"^[A-Za-z0-9_\-]{1,64}$")  # keys.check_name's rule, without its exception

MESSAGES = Counter("kmvipe_bus_messages", "Bus messages received (decoded) and published",
                   ["direction", "stream", "topic"])
BYTES = Counter("kmvipe_bus_bytes", "Payload bytes of the bus messages counted in kmvipe_bus_messages_total",
                ["direction", "stream", "topic"])
BAD_PAYLOADS = Counter("kmvipe_bus_bad_payloads", "Payloads dropped: undecodable, unexpected or failing their "
                       "handler", ["stream", "topic", "reason"])
QUERIES = Counter("kmvipe_bus_queries", "Queries received by this process's queryables", ["stream", "topic"])
INBOX_DROPPED = Counter("kmvipe_inbox_dropped", "Messages a real-time inbox dropped to make room",
                        ["stream", "kind"])
INBOX_OVERFLOWED = Counter("kmvipe_inbox_overflowed", "Messages a full inbox kept past its bound", ["stream"])
STAGE_LATENCY = Histogram("kmvipe_stage_latency_seconds", "From a frame's arrival at this stage (frame, frame_lite "
                          "or keyframe) to the first message the stage published about it", ["stream", "topic"],
                          buckets=LATENCY_BUCKETS)


def key_labels(key: str) -> tuple[str, str]:
    """``(stream, topic)`` of a bus key: ``kmvipe/cam0/frame`` → ``("cam0", "frame")``, the map's queryables →
    ``map/<name>``, a source token → ``@source``; anything else → ``("", "other")`` (bounded labels)."""
    parts = key.split("/")
    if len(parts) < 3 or parts[0] != keys.ROOT:
        return "", OTHER
    stream = parts[1] if _STREAM.match(parts[1]) else OTHER
    topic = parts[2]
    if topic == keys.MAP and len(parts) == 4 and _STREAM.match(parts[3]):
        return stream, f"{keys.MAP}/{parts[3]}"
    return stream, topic if topic in _KNOWN_TOPICS else OTHER


_LABELS: dict[str, tuple[str, str]] = {}
_CHILDREN: dict[tuple[str, str], tuple] = {}  # (direction, key) -> (messages child, bytes child)


def _labels(key: str) -> tuple[str, str]:
    labels = _LABELS.get(key)
    if labels is None:
        labels = key_labels(key)
        if len(_LABELS) < MAX_CACHED_KEYS:
            _LABELS[key] = labels
    return labels


def count_message(direction: str, key: str, nbytes: int) -> None:
    """One message in or out on ``key`` (the bus's hot path: a dict lookup and two increments)."""
    children = _CHILDREN.get((direction, key))
    if children is None:
        labels = (direction, *_labels(key))
        children = MESSAGES.labels(*labels), BYTES.labels(*labels)
        if len(_CHILDREN) < MAX_CACHED_KEYS:
            _CHILDREN[(direction, key)] = children
    children[0].inc()
    children[1].inc(nbytes)


def count_bad_payload(key: str, reason: str) -> None:
    BAD_PAYLOADS.labels(*_labels(key), reason).inc()


def count_query(key: str) -> None:
    QUERIES.labels(*_labels(key)).inc()


def count_inbox_drop(key: str, kind: str) -> None:
    INBOX_DROPPED.labels(_labels(key)[0], kind).inc()


def count_inbox_overflow(key: str) -> None:
    INBOX_OVERFLOWED.labels(_labels(key)[0]).inc()


class StageClock:
    """A frame's time in one stage: from the first arrival of ``(stream, seq)`` on a frame-carrying topic
    (:data:`STAGE_INPUTS`) to the first message this bus publishes with that ``seq`` (features: the keyframe or
    frame_lite; ba: the tracked pose; mapstore: its progress once the keyframe is committed).

    Frames that never lead to a message (dropped, merged) are forgotten oldest first past ``capacity``.
    ``t_ns`` cannot serve here: it is the source's media time (a file's frame index over its rate), not a clock
    every process shares."""

    def __init__(self, capacity: int = MAX_CACHED_KEYS):
        self.capacity = capacity
        self._arrived: dict[tuple[str, int], float] = {}
        self._lock = threading.Lock()

    def arrived(self, key: str, seq: int) -> None:
        stream, topic = _labels(key)
        if topic not in STAGE_INPUTS:
            return
        with self._lock:
            if (stream, seq) not in self._arrived:
                self._arrived[(stream, seq)] = time.monotonic()
                if len(self._arrived) > self.capacity:
                    del self._arrived[next(iter(self._arrived))]

    def published(self, key: str, seq: int) -> None:
        stream, topic = _labels(key)
        if topic in NOT_STAGE_OUTPUTS:
            return
        with self._lock:
            started = self._arrived.pop((stream, seq), None)
        if started is not None:
            STAGE_LATENCY.labels(stream, topic).observe(time.monotonic() - started)


class _Queue(Protocol):
    last_key: str | None

    def qsize(self) -> int: ...


class _InboxDepth:
    """``kmvipe_inbox_depth{stream}``: the live inboxes' queued messages, read at scrape time."""

    def __init__(self) -> None:
        self._inboxes: weakref.WeakSet = weakref.WeakSet()
        self._lock = threading.Lock()

    def track(self, inbox: _Queue) -> None:
        with self._lock:
            self._inboxes.add(inbox)

    def collect(self) -> Iterator[GaugeMetricFamily]:
        with self._lock:
            inboxes = list(self._inboxes)
        depth: dict[str, int] = {}
        for inbox in inboxes:
            if inbox.last_key is not None:  # an inbox that never received has no stream yet
                stream = _labels(inbox.last_key)[0]
                depth[stream] = depth.get(stream, 0) + inbox.qsize()
        family = GaugeMetricFamily("kmvipe_inbox_depth", "Messages waiting in the service's inboxes", labels=["stream"])
        for stream, n in sorted(depth.items()):
            family.add_metric([stream], n)
        yield family


class _PeakRss:
    def collect(self) -> Iterator[GaugeMetricFamily]:
        # ru_maxrss is in KiB on Linux
        yield GaugeMetricFamily("kmvipe_process_peak_rss_bytes", "Peak resident memory of this process",
                                value=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024)


INBOXES = _InboxDepth()
REGISTRY.register(INBOXES)
REGISTRY.register(_PeakRss())


class Probe(Protocol):
    """What the health endpoints ask (a :class:`bus.Bus`)."""

    service: str
    instance: str

    @property
    def is_open(self) -> bool: ...

    @property
    def is_ready(self) -> bool: ...


class _ProbeCollector:
    def __init__(self, probe: Probe):
        self.probe = probe

    def collect(self) -> Iterator[GaugeMetricFamily]:
        yield GaugeMetricFamily("kmvipe_ready", "1 once the service declared itself ready (its subscriptions exist)",
                                value=float(self.probe.is_ready))
        info = GaugeMetricFamily("kmvipe_service_info", "The service and instance this process is",
                                 labels=["service", "instance"])
        info.add_metric([self.probe.service, self.probe.instance], 1)
        yield info


class _Handler(BaseHTTPRequestHandler):
    server: "HealthServer"

    def do_GET(self) -> None:  # noqa: N802 - http.server's name
        path = self.path.split("?", 1)[0]
        if path == "/metrics":
            body = generate_latest(self.server.registry) + generate_latest(self.server.own)
            return self._answer(200, body, CONTENT_TYPE_LATEST)
        if path == "/livez":
            live = self.server.probe.is_open
            return self._answer(200 if live else 503, b"ok\n" if live else b"bus session closed\n")
        if path == "/readyz":
            ready = self.server.probe.is_open and self.server.probe.is_ready
            return self._answer(200 if ready else 503, b"ready\n" if ready else b"not ready\n")
        self._answer(404, b"not found: /metrics, /livez, /readyz\n")

    def _answer(self, status: int, body: bytes, content_type: str = "text/plain; charset=utf-8") -> None:
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, format: str, *args) -> None:  # probes every few seconds: not worth a log line
        pass


class HealthServer(ThreadingHTTPServer):
    """``/metrics``, ``/livez`` and ``/readyz`` of one process on ``host:port`` (port 0: any free port), served
    from a daemon thread."""

    daemon_threads = True

    def __init__(self, probe: Probe, host: str, port: int, registry: CollectorRegistry = REGISTRY):
        try:
            super().__init__((host, port), _Handler)
        except OSError as exc:
            raise ConfigError(f"cannot serve metrics and health on {host}:{port} ({exc}): give each process on "
                              "this host its own KMVIPE_METRICS_PORT, or 0 to turn the endpoints off") from exc
        self.probe, self.registry = probe, registry
        self.own = CollectorRegistry(auto_describe=True)
        self.own.register(_ProbeCollector(probe))
        self._thread = threading.Thread(target=self.serve_forever, name="metrics-http", daemon=True)

    def server_bind(self) -> None:
        socketserver.TCPServer.server_bind(self)  # HTTPServer's would also look the host's name up in DNS
        self.server_name, self.server_port = self.server_address[:2]

    @property
    def port(self) -> int:
        return self.server_address[1]

    def start(self) -> "HealthServer":
        self._thread.start()
        return self

    def close(self) -> None:
        if self._thread.is_alive():
            self.shutdown()
            self._thread.join(timeout=5)
        self.server_close()


@contextlib.contextmanager
def serving(settings: MetricsSettings, probe: Probe) -> Iterator[HealthServer | None]:
    """Serve the endpoints while the block runs when ``settings.port`` is set; 0 serves nothing."""
    if not settings.port:
        yield None
        return
    server = HealthServer(probe, settings.host, settings.port).start()
    log.info("metrics and health endpoints up", extra={"host": settings.host, "port": server.port})
    try:
        yield server
    finally:
        server.close()
