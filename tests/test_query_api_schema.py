"""Property-based tests of the OpenAPI spec with schemathesis: whatever the generated request (valid or not),
the gateway never answers 5xx, and every 4xx carries a ``detail`` that says what is wrong."""
from __future__ import annotations

from collections import Counter

import pytest

schemathesis = pytest.importorskip("schemathesis")
from hypothesis import HealthCheck, given, settings  # noqa: E402

from services.query_api.app import create_app  # noqa: E402
from services.query_api.gateway import Gateway  # noqa: E402
from tests.query_api_fixtures import STREAM, bus_pair, make_scene, oracle_settings, scene_map, wait_for  # noqa: E402


@pytest.fixture(scope="module")
def api_schema():
    map_bus, gw_bus = bus_pair()
    scene_map(make_scene(points_per_label=50)).serve(map_bus, STREAM)
    cfg = oracle_settings(timeout_s=2.0, max_body_bytes=256 * 1024)
    gw = Gateway(cfg, gw_bus)
    wait_for(lambda: gw.maps.stats(STREAM), what="the map queryable")
    yield schemathesis.openapi.from_asgi("/openapi.json", create_app(cfg, gw))
    map_bus.close()
    gw_bus.close()


SETTINGS = settings(max_examples=50, deadline=None, database=None, suppress_health_check=list(HealthCheck))


def _check(case, seen: Counter) -> None:
    response = case.call()
    seen[response.status_code // 100] += 1
    where = f"{case.method} {case.formatted_path}"
    assert response.status_code < 500, f"{where} → {response.status_code}: {response.text[:300]}"
    if 400 <= response.status_code < 500:
        assert response.json().get("detail"), f"{where} → {response.status_code} without a detail: {response.text[:300]}"


def test_no_server_errors_and_4xx_explain_themselves(api_schema):
    operations = [result.ok() for result in api_schema.get_all_operations()]
    assert len(operations) >= 8
    seen: Counter = Counter()
    for operation in operations:
        def check(case):
            _check(case, seen)

        given(case=operation.as_strategy())(SETTINGS(check))()
    print(f"\nschemathesis: {sum(seen.values())} requests over {len(operations)} operations, by status class {dict(seen)}")
    assert seen[2] > 0 and seen[4] > 0  # both valid and invalid requests were generated and answered
