"""ASGI middleware of the gateway: request body size limit and Prometheus metrics (prometheus-fastapi-instrumentator
times every request and finds its route; the gateway's own series are filled from what it measured)."""
from __future__ import annotations

import json

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram
from prometheus_fastapi_instrumentator.metrics import Info
from prometheus_fastapi_instrumentator.middleware import PrometheusInstrumentatorMiddleware


class BodyLimit:
    """Refuse (413) requests whose body is larger than ``max_bytes``: by Content-Length up front, else while
    the body streams in (chunked uploads)."""

    def __init__(self, app, max_bytes: int):
        self.app, self.max_bytes = app, max_bytes

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        length = dict(scope.get("headers", [])).get(b"content-length")
        if length is not None and length.isdigit() and int(length) > self.max_bytes:
            return await _too_large(send, int(length), self.max_bytes)
        seen, too_large = 0, False

        async def guarded_receive():
            nonlocal seen, too_large
            message = await receive()
            if message["type"] == "http.request" and not too_large:
                seen += len(message.get("body", b""))
                if seen > self.max_bytes:  # stop reading: the app sees a cut body, the client gets a 413
                    too_large = True
                    return {"type": "http.request", "body": b"", "more_body": False}
            return message

        async def guarded_send(message):
            if not too_large:
                await send(message)
            elif message["type"] == "http.response.start":
                await _too_large(send, seen, self.max_bytes)  # replaces whatever the app answered

        await self.app(scope, guarded_receive, guarded_send)


async def _too_large(send, size: int, limit: int) -> None:
    body = json.dumps({"detail": f"request body of {size}+ bytes exceeds the limit of {limit} bytes "
                                 "(KMVIPE_QUERY_MAX_BODY_BYTES)"}).encode()
    await send({"type": "http.response.start", "status": 413,
                "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]})
    await send({"type": "http.response.body", "body": body})


class Metrics:
    """Per-app Prometheus registry: requests by route and status, latency by route."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        self.requests = Counter("kmvipe_http_requests_total", "HTTP requests", ["route", "method", "status"],
                                registry=self.registry)
        self.latency = Histogram("kmvipe_http_request_seconds", "HTTP request latency", ["route", "method"],
                                 registry=self.registry,
                                 buckets=(0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10))
        self.text_cache = Gauge("kmvipe_text_embedding_cache", "Text embedding cache: hits, misses, size",
                                ["what"], registry=self.registry)

    def observe(self, info: Info) -> None:
        """One finished request (its route template, or ``none`` when no route matched)."""
        self.requests.labels(info.modified_handler, info.method, info.modified_status).inc()
        self.latency.labels(info.modified_handler, info.method).observe(info.modified_duration)


class MetricsMiddleware(PrometheusInstrumentatorMiddleware):
    """The instrumentator's middleware, what ``Instrumentator(...).instrument(app)`` adds, filling the gateway's
    series (their names and ``route`` label are what dashboards read) with exact status codes."""

    def __init__(self, app, metrics: Metrics):
        super().__init__(app, should_group_status_codes=False, instrumentations=[metrics.observe],
                         registry=metrics.registry)
