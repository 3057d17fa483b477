"""The FastAPI application: /v1 routes, error mapping, API key, CORS, body limit, metrics, the web viewer."""
from __future__ import annotations

import logging
import secrets
from pathlib import Path

from fastapi import Depends, FastAPI, HTTPException, Request
from fastapi.middleware.cors import CORSMiddleware
from fastapi.responses import FileResponse, JSONResponse, Response
from fastapi.security import APIKeyHeader
from fastapi.staticfiles import StaticFiles
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from ..common.errors import ServiceTimeout
from .api.keyframes import router as keyframes_router
from .api.middleware import BodyLimit, Metrics, MetricsMiddleware
from .api.routes import public, router
from .config import QuerySettings
from .core.text import UnknownLabel
from .gateway import ExampleUnavailable, Gateway
from .mapclient import MapServiceError, StreamNotFound
from .textpath import SpaceMismatch, TextUnavailable

log = logging.getLogger(__name__)
STATIC = Path(__file__).resolve().parent / "static"
API_KEY = APIKeyHeader(name="X-API-Key", auto_error=False, description="Required when the gateway has an API key.")

# error → (HTTP status, prefix); the message of the error follows the prefix
ERROR_STATUS: dict[type[Exception], tuple[int, str]] = {
    StreamNotFound: (404, ""),
    UnknownLabel: (422, ""),
    SpaceMismatch: (409, "text query refused: "),
    TextUnavailable: (503, ""),
    ExampleUnavailable: (503, ""),
    MapServiceError: (502, ""),
    ServiceTimeout: (504, "timeout: "),
}


def _require_key(request: Request, key: str | None = Depends(API_KEY)) -> None:
    expected = request.app.state.settings.api_key
    if expected and not (key and secrets.compare_digest(key.encode(), expected.encode())):
        raise HTTPException(401, "missing or wrong X-API-Key header", headers={"WWW-Authenticate": "APIKey"})


def create_app(cfg: QuerySettings, gateway: Gateway) -> FastAPI:
    """The gateway's ASGI app; ``gateway`` does the work (tests pass one wired to a loopback bus)."""
    app = FastAPI(title="KM-ViPE query API", version="1.0",
                  description="Ask the live semantic map of each camera stream in natural language or by example.")
    app.state.settings, app.state.gateway, app.state.metrics = cfg, gateway, Metrics()
    app.include_router(router, dependencies=[Depends(_require_key)])
    app.include_router(keyframes_router, dependencies=[Depends(_require_key)])
    app.include_router(public)
    for exc_type, (status, prefix) in ERROR_STATUS.items():
        app.add_exception_handler(exc_type, _handler(status, prefix))

    @app.get("/metrics", include_in_schema=True, summary="Prometheus metrics",
             dependencies=[Depends(_require_key)], response_class=Response,
             responses={200: {"content": {"text/plain": {}}}})
    def metrics(request: Request) -> Response:
        _cache_metrics(request.app)
        return Response(generate_latest(request.app.state.metrics.registry), media_type=CONTENT_TYPE_LATEST)

    @app.get("/", include_in_schema=False)
    def viewer() -> FileResponse:
        return FileResponse(STATIC / "index.html")

    app.mount("/static", StaticFiles(directory=STATIC), name="static")
    app.add_middleware(MetricsMiddleware, metrics=app.state.metrics)
    if cfg.cors_origins:
        app.add_middleware(CORSMiddleware, allow_origins=cfg.cors_origins, allow_methods=["GET", "POST"],
                           allow_headers=["Content-Type", "X-API-Key"])
    app.add_middleware(BodyLimit, max_bytes=cfg.max_body_bytes)
    return app


def _handler(status: int, prefix: str):
    async def handle(request: Request, exc: Exception) -> JSONResponse:
        log.info("request refused", extra={"path": request.url.path, "status": status, "error": str(exc)})
        return JSONResponse({"detail": prefix + str(exc)}, status_code=status)

    return handle


def _cache_metrics(app: FastAPI) -> None:
    """Copy the text embedding cache counters into the metrics (never loads the text models)."""
    embedder = app.state.gateway.text.loaded()
    if embedder is not None:
        info = embedder.info()
        gauge = app.state.metrics.text_cache
        gauge.labels("hit").set(info.hits)
        gauge.labels("miss").set(info.misses)
        gauge.labels("size").set(info.size)
