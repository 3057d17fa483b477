"""The gateway's API key: the liveness probe answers without it, every other API route refuses a request
without it or with a wrong one (401), so a route added later without the guard fails here."""
from __future__ import annotations

import pytest
from fastapi.testclient import TestClient

from services.common.bus import Bus
from services.common.config import BusSettings
from services.query_api.app import create_app
from services.query_api.config import QuerySettings
from services.query_api.gateway import Gateway

KEY = "s3cret-key"
PUBLIC = {"/v1/health"}


@pytest.fixture(scope="module")
def app():
    cfg = QuerySettings(api_key=KEY, text_encoder="none", alive_timeout_s=0.2, timeout_s=0.5)
    bus = Bus(BusSettings(mode="peer", listen=["tcp/127.0.0.1:0"]), "query_api")  # a bus of its own, no peers
    yield create_app(cfg, Gateway(cfg, bus))
    bus.close()


def api_routes(app) -> list[tuple[str, str]]:
    """(method, path) of every route in the OpenAPI document, path parameters filled in."""
    return [(method.upper(), path.replace("{stream}", "cam0"))
            for path, ops in app.openapi()["paths"].items() for method in ops]


def test_health_answers_without_the_key(app):
    with TestClient(app) as client:
        for headers in ({}, {"X-API-Key": "wrong"}):
            res = client.get("/v1/health", headers=headers)
            assert res.status_code == 200 and "query_api" in res.json()["services"]


def test_every_other_route_needs_the_key(app):
    guarded = [(m, p) for m, p in api_routes(app) if p not in PUBLIC]
    assert {("GET", "/metrics"), ("GET", "/v1/streams"), ("POST", "/v1/streams/cam0/query")} <= set(guarded)
    with TestClient(app) as client:
        for method, path in guarded:
            for headers in ({}, {"X-API-Key": "wrong"}, {"X-API-Key": KEY[:-1]}):
                res = client.request(method, path, headers=headers)
                assert res.status_code == 401, f"{method} {path} with {headers}: {res.status_code}"
                assert res.headers["www-authenticate"] == "APIKey"


def test_the_right_key_opens_the_api(app):
    with TestClient(app) as client:
        assert client.get("/v1/streams", headers={"X-API-Key": KEY}).json() == {"streams": []}
        assert client.get("/metrics", headers={"X-API-Key": KEY}).status_code == 200
