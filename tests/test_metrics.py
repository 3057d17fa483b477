"""Metrics and health endpoints (services/common/metrics.py): real Bus sessions on loopback and real HTTP. Messages
in and out are counted under their stream and topic, bad payloads and inbox drops too, /readyz says 503 until the
service declared itself ready, and a real `kmvipe service mapstore` with KMVIPE_METRICS_PORT answers all three.
Also the gateway's HTTP metrics (services/query_api/api/middleware.py)."""
from __future__ import annotations

import json
import logging
import os
import socket
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
import uuid
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from fastapi import FastAPI, HTTPException
from fastapi.responses import StreamingResponse
from fastapi.testclient import TestClient
from prometheus_client import generate_latest
from prometheus_client.parser import text_string_to_metric_families

from services.common import keys, metrics
from services.common.bus import Bus, Delivery, Inbox
from services.common.config import BusSettings, MetricsSettings
from services.common.errors import ConfigError
from services.common.schema import Credit, FrameLite, Keyframe, Poses, encode
from services.common.service_main import StreamField
from services.query_api.api.middleware import Metrics, MetricsMiddleware
from tests.conftest import wait_until
from tests.helpers.processes import stop_cleanly

KMVIPE = Path(sys.executable).with_name("kmvipe")
K = np.array([10.0, 10.0, 4.0, 4.0])
# no proxy for loopback, whatever the environment says
_HTTP = urllib.request.build_opener(urllib.request.ProxyHandler({}))


def _stream() -> str:
    return f"m{uuid.uuid4().hex[:10]}"  # counters are process-wide: each test its own stream


def _get(url: str) -> tuple[int, str]:
    try:
        with _HTTP.open(url, timeout=5) as reply:
            return reply.status, reply.read().decode()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.read().decode()


def _value(text: str, name: str, **labels: str) -> float | None:
    """The sample ``name`` whose labels include ``labels`` in a /metrics text; None when absent."""
    for family in text_string_to_metric_families(text):
        for sample in family.samples:
            if sample.name == name and labels.items() <= sample.labels.items():
                return sample.value
    return None


def _lite(stream: str, seq: int) -> FrameLite:
    return FrameLite(stream, seq, seq, image=np.zeros((4, 4), np.uint8), intrinsics=K)


@pytest.fixture
def buses(tcp_endpoint):
    """A source (peer, listening) and a stage (client) with its endpoints on a free port."""
    with Bus(BusSettings(mode="peer", listen=[tcp_endpoint]), "ingest") as source, \
            Bus(BusSettings(mode="client", connect=[tcp_endpoint]), "ba") as stage:
        server = metrics.HealthServer(stage, "127.0.0.1", 0).start()
        try:
            yield source, stage, f"http://127.0.0.1:{server.port}"
        finally:
            server.close()


def _await_subscriber(source: Bus, key: str) -> None:
    """Wait until ``source`` knows of a subscriber to ``key``, so every message it publishes next arrives."""
    publisher = source.session.declare_publisher(key)
    try:
        wait_until(lambda: publisher.matching_status.matching, 10, f"a subscriber on {key}")
    finally:
        publisher.undeclare()


def test_messages_in_and_out_are_counted_under_their_stream_and_topic(buses):
    source, stage, url = buses
    stream = _stream()
    key = keys.topic(stream, keys.FRAME_LITE)
    box = stage.inbox({key: [FrameLite]}, maxsize=64)
    _await_subscriber(source, key)
    frames = [_lite(stream, seq) for seq in (0, 1, 2, 2, 3)]  # a frame sent twice: counted twice, timed once
    for frame in frames:
        source.publish(key, frame)
    wait_until(lambda: box.qsize() == len(frames), 5, "every frame in the inbox")

    text = _get(f"{url}/metrics")[1]
    for direction in ("out", "in"):
        assert _value(text, "kmvipe_bus_messages_total", direction=direction, stream=stream,
                      topic="frame_lite") == len(frames)
        assert _value(text, "kmvipe_bus_bytes_total", direction=direction, stream=stream,
                      topic="frame_lite") == sum(len(encode(f)) for f in frames)
    assert _value(text, "kmvipe_inbox_depth", stream=stream) == len(frames)

    seqs = []
    while (delivery := box.get(0)) is not None:
        seqs.append(delivery.msg.seq)
        stage.publish(keys.topic(stream, keys.CREDIT), Credit(stream, delivery.msg.seq, 0))  # a heartbeat: no stop
        stage.publish(keys.topic(stream, keys.POSE), Poses(
            stream, delivery.msg.seq, 0, frame_seqs=np.array([delivery.msg.seq]), stamps_ns=np.array([0]),
            poses=np.eye(4)[None]))
    text = _get(f"{url}/metrics")[1]
    assert _value(text, "kmvipe_inbox_depth", stream=stream) == 0
    assert _value(text, "kmvipe_bus_messages_total", direction="out", stream=stream, topic="pose") == len(seqs)
    # each frame's first pose stops its clock, once per frame; credit never does
    assert _value(text, "kmvipe_stage_latency_seconds_count", stream=stream, topic="pose") == len(set(seqs)) == 4
    assert _value(text, "kmvipe_stage_latency_seconds_count", stream=stream, topic="credit") is None


def test_bad_payloads_are_counted_by_reason(buses):
    source, stage, url = buses
    stream = _stream()
    key = keys.topic(stream, keys.FRAME_LITE)

    def handler(delivery: Delivery) -> None:
        if delivery.msg.seq == 13:
            raise ValueError("unlucky frame")

    stage.subscribe(key, handler, [FrameLite])
    _await_subscriber(source, key)
    source.put(key, b"\x93not a message")
    source.publish(key, Keyframe(stream, 1, 1, image=np.zeros((8, 8, 3), np.uint8), intrinsics=K))  # wrong kind
    source.publish(key, _lite(stream, 12))
    source.publish(key, _lite(stream, 13))
    wait_until(lambda: stage.stats.total == 3, 5, "three bad payloads")

    text = _get(f"{url}/metrics")[1]
    assert _value(text, "kmvipe_bus_bad_payloads_total", stream=stream, topic="frame_lite", reason="decode") == 2
    assert _value(text, "kmvipe_bus_bad_payloads_total", stream=stream, topic="frame_lite", reason="handler") == 1
    # both frames were received (one failed its handler); the undecodable payloads were not
    assert _value(text, "kmvipe_bus_messages_total", direction="in", stream=stream, topic="frame_lite") == 2


def test_readyz_answers_503_until_the_service_is_ready_and_livez_follows_the_session(tcp_endpoint):
    bus = Bus(BusSettings(mode="peer", listen=[tcp_endpoint]), "mapstore")
    server = metrics.HealthServer(bus, "127.0.0.1", 0).start()
    url = f"http://127.0.0.1:{server.port}"
    try:
        assert _get(f"{url}/livez")[0] == 200
        assert _get(f"{url}/readyz")[0] == 503
        assert _value(_get(f"{url}/metrics")[1], "kmvipe_ready") == 0
        bus.ready()
        assert _get(f"{url}/readyz")[0] == 200
        text = _get(f"{url}/metrics")[1]
        assert _value(text, "kmvipe_ready") == 1
        assert _value(text, "kmvipe_service_info", service="mapstore", instance=bus.instance) == 1
        assert _get(f"{url}/nothing")[0] == 404
        bus.close()
        assert _get(f"{url}/livez")[0] == 503
        assert _get(f"{url}/readyz")[0] == 503
    finally:
        server.close()
        if bus.is_open:
            bus.close()


def test_inbox_drops_and_overflows_are_counted_per_stream():
    stream = _stream()
    value = metrics.REGISTRY.get_sample_value
    realtime, lossless = Inbox(2, lossless=False, droppable=(FrameLite,)), Inbox(2, lossless=True)
    for seq in range(5):
        delivery = Delivery(keys.topic(stream, keys.FRAME_LITE), _lite(stream, seq))
        realtime.put(delivery)
        lossless.put(delivery)
    assert value("kmvipe_inbox_dropped_total", {"stream": stream, "kind": "frame_lite"}) == 3 == realtime.dropped
    assert value("kmvipe_inbox_overflowed_total", {"stream": stream}) == 3 == lossless.overflowed
    assert value("kmvipe_inbox_depth", {"stream": stream}) == 2 + 5


def test_a_taken_port_is_a_clear_configuration_error():
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        probe = SimpleNamespace(service="ba", instance="x", is_open=True, is_ready=True)
        with pytest.raises(ConfigError, match="KMVIPE_METRICS_PORT"):
            metrics.HealthServer(probe, "127.0.0.1", taken.getsockname()[1])


def test_endpoints_are_off_unless_a_port_is_set(monkeypatch, tmp_path):
    monkeypatch.chdir(tmp_path)  # no .env file
    monkeypatch.delenv("KMVIPE_METRICS_PORT", raising=False)
    with metrics.serving(MetricsSettings(), SimpleNamespace()) as server:
        assert server is None


def test_log_lines_of_a_stream_thread_carry_the_stream():
    records: list[logging.LogRecord] = []
    handler = logging.Handler()
    handler.emit = records.append
    handler.addFilter(StreamField())
    logger = logging.getLogger("tests.metrics.stream_field")
    logger.addHandler(handler)
    logger.propagate = False

    def log_on(thread_name: str, **extra) -> None:
        thread = threading.Thread(target=lambda: logger.warning("x", extra=extra), name=thread_name)
        thread.start()
        thread.join()

    try:
        log_on("stream-cam7")
        log_on("stream-cam-7_b/tracking")
        log_on("stream-cam7", stream="named")
        log_on("semantics")
    finally:
        logger.removeHandler(handler)
    assert [getattr(r, "stream", None) for r in records] == ["cam7", "cam-7_b", "named", None]


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@pytest.mark.timeout(120)
def test_a_service_process_serves_its_metrics_and_health(tmp_path, tcp_endpoint):
    port, stream = _free_port(), _stream()
    env = {k: v for k, v in os.environ.items() if not k.startswith("KMVIPE_")}
    env.update({"KMVIPE_BUS_MODE": "client", "KMVIPE_BUS_CONNECT": json.dumps([tcp_endpoint]),
                "KMVIPE_BUS_LISTEN": "[]", "KMVIPE_METRICS_PORT": str(port), "KMVIPE_MAPSTORE_DEVICE": "cpu",
                "KMVIPE_MAPSTORE_DB_PATH": str(tmp_path / "{stream}.db"),
                "KMVIPE_MAPSTORE_EXPORT_DIR": str(tmp_path / "export"), "PYTHONUNBUFFERED": "1"})
    url = f"http://127.0.0.1:{port}"
    log_path = tmp_path / "mapstore.log"
    with Bus(BusSettings(mode="router", listen=[tcp_endpoint]), "test") as bus:
        proc = subprocess.Popen([str(KMVIPE), "service", "mapstore"], env=env, cwd=tmp_path,
                                stdout=log_path.open("wb"), stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
        try:
            def answers(path: str) -> int | None:
                assert proc.poll() is None, log_path.read_text()
                try:
                    return _get(url + path)[0]
                except OSError:  # not listening yet
                    return None

            wait_until(lambda: answers("/readyz") == 200, 90, "/readyz 200", poll=0.2)
            assert "mapstore" in bus.alive()  # ready over HTTP is ready on the bus
            assert answers("/livez") == 200
            # a source announces a stream and sends garbage: the stream's worker counts it under its stream
            token = bus.announce(stream)
            key = keys.topic(stream, keys.KEYFRAME)

            def counted() -> bool:
                bus.put(key, b"\x93garbage")
                text = _get(url + "/metrics")[1]
                return (_value(text, "kmvipe_bus_bad_payloads_total", stream=stream, topic="keyframe") or 0) > 0

            wait_until(counted, 30, "the garbage counted", poll=0.2)
            text = _get(url + "/metrics")[1]
            assert _value(text, "process_resident_memory_bytes") > 10e6
            assert _value(text, "kmvipe_process_peak_rss_bytes") >= _value(text, "process_resident_memory_bytes")
            assert _value(text, "kmvipe_service_info", service="mapstore") == 1
            token.undeclare()
        finally:
            stop_cleanly(proc, log_path)


def test_the_gateway_counts_requests_by_route_template_and_exact_status():
    """The gateway's middleware (prometheus-fastapi-instrumentator, services/query_api/api/middleware.py) on a small
    app: requests counted under their route template, 404s apart from 200s, an unmatched path under ``none``, a
    streamed body timed to its end."""
    app, gauges = FastAPI(), Metrics()

    @app.get("/items/{item}")
    def item(item: int) -> dict:
        if item < 0:
            raise HTTPException(404, "no such item")
        return {"item": item}

    @app.get("/slow")
    def slow() -> StreamingResponse:
        def body():
            yield b"a"
            time.sleep(0.3)
            yield b"b"
        return StreamingResponse(body())

    app.add_middleware(MetricsMiddleware, metrics=gauges)
    with TestClient(app) as client:
        for path in ("/items/1", "/items/2", "/items/-1", "/nowhere"):
            client.get(path)
        assert client.get("/slow").content == b"ab"
    text = generate_latest(gauges.registry).decode()
    requests = "kmvipe_http_requests_total"
    assert _value(text, requests, route="/items/{item}", method="GET", status="200") == 2
    assert _value(text, requests, route="/items/{item}", method="GET", status="404") == 1
    assert _value(text, requests, route="none", method="GET", status="404") == 1
    assert _value(text, "kmvipe_http_request_seconds_sum", route="/slow") >= 0.3
    assert _value(text, "kmvipe_http_request_seconds_count", route="/items/{item}") == 3
