"""The docker-compose deployment without docker: the secured router from the router config compose mounts, and
features, ba, mapstore and query_api started with the command and environment docker-compose.yml gives them
(read from the file itself, so the test fails when it drifts), then three edge cameras and a malformed fourth
stream through the secured bus, checked over HTTP only.

Only what is host-specific is swapped: the router's address and port, ``/run/secrets/...`` for the files the
bus commands made (as compose's ``secrets:`` maps them), volume paths for temporary folders, the ports of the
gateway and of the metrics endpoints (free ones), and 0.0.0.0 for loopback. The processes run from the
production venv (``$KMVIPE_PROD_VENV``, as in tests/test_production_install.py; required where
``KMVIPE_REQUIRE_PROD_VENV=1``), else from this venv. Reading compose and the Dockerfile, the operator's commands
and the processes: tests/helpers/compose_deployment.py.
"""
from __future__ import annotations

import os
import secrets
import threading
import time
from pathlib import Path

import httpx
import pytest

from services.common import keys
from services.common.acl import edge_user
from services.common.bus import Bus
from services.common.config import BusSettings
from services.runner.children import free_tcp_endpoint
from tests.conftest import wait_until
from tests.helpers.compose_deployment import (Compose, Processes, base_env, dockerfile_image, edge_env,
                                              make_secrets, router_changes, service_env, start_router, venv_bin)

SPEC = "synth:frames=24,width=256,height=192"
FRAMES = 24
CAMERAS = ("cam1", "cam2", "cam3")
JUNK = "junk"
SERVICES = ("features", "ba", "mapstore", "query_api")  # compose's ingest is idle without a source: not started
READY_S = 60.0
FINISH_BOUND_S = 60.0
"""From the publishers' start until every camera has all its frames posed and a map. Measured here (2 cores shared
with other work): 4-20 s with the junk stream, 10-15 s without it; a stream held up behind junk (a worker shared with
it, a loop blocked on it) would not finish at all."""
MIN_KEYFRAMES = 3


class Junk:
    """A fourth source with its own edge credential: announces its stream and puts garbage on its frame key for as
    long as it runs (a client publisher only sends once it has heard of a subscriber, so it keeps putting)."""

    def __init__(self, router: str, secret_dir: Path):
        user = edge_user(JUNK)
        self.bus = Bus(BusSettings(mode="client", connect=[router], tls_root_ca=secret_dir / "ca.pem", user=user,
                                   password_file=secret_dir / f"{user}.password"), "ingest")
        self.token = self.bus.announce(JUNK)
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._garbage, daemon=True)
        self.thread.start()

    def _garbage(self) -> None:
        while not self.stop.wait(0.02):
            self.bus.put(keys.topic(JUNK, keys.FRAME), b"\x93\xa5junk!" + os.urandom(64))

    def close(self) -> None:
        self.stop.set()
        self.thread.join(timeout=5)
        self.token.undeclare()
        self.bus.close()


class Watch:
    """What the gateway reports over HTTP while the streams run: posed frames and the map of every stream, and
    when each camera was done (all its frames posed and a map with keyframes and their semantic codes)."""

    def __init__(self, http: httpx.Client):
        self.http = http
        self.posed: dict[str, set[int]] = {s: set() for s in (*CAMERAS, JUNK)}
        self.maps: dict[str, dict | None] = {}
        self.done_at: dict[str, float] = {}

    def poll(self) -> bool:
        maps = {entry["name"]: entry["map"] for entry in self._get("/v1/streams").json()["streams"]}
        for stream in (s for s in (*CAMERAS, JUNK) if s not in self.done_at):
            answer = self._get(f"/v1/streams/{stream}/trajectory", allow=(404,))  # 404: no pose yet
            if answer.status_code == 200:
                self.posed[stream] |= {f["seq"] for f in answer.json()["frames"]}
            self.maps[stream] = maps.get(stream)
            if self.posed[stream] >= set(range(FRAMES)) and mapped(self.maps[stream]):
                self.done_at[stream] = time.monotonic()
        return set(CAMERAS) <= set(self.done_at)

    def _get(self, path: str, allow: tuple[int, ...] = ()) -> httpx.Response:
        answer = self.http.get(path)
        assert answer.status_code in (200, *allow), f"GET {path}: {answer.status_code} {answer.text}"
        return answer


def mapped(stats: dict | None) -> bool:
    """A map of the stream's own keyframes, fused, with the codes the semantics sent (a PCA basis)."""
    return (stats is not None and stats["keyframes"] >= MIN_KEYFRAMES and stats["points"] > 0
            and stats["pca_version"] >= 0)


def check_the_key(url: str, key: str) -> None:
    """/v1/health is the open liveness probe; everything else needs the key."""
    assert httpx.get(f"{url}/v1/health", timeout=10).status_code == 200
    for path in ("/v1/streams", f"/v1/streams/{CAMERAS[0]}/trajectory", "/metrics"):
        for headers in ({}, {"X-API-Key": "not-" + key}):
            status = httpx.get(url + path, headers=headers, timeout=10).status_code
            assert status == 401, f"GET {path} with {headers or 'no key'}: {status}"


@pytest.mark.slow
@pytest.mark.timeout(180)
def test_compose_topology_serves_three_cameras_beside_a_malformed_stream(tmp_path):
    bin_dir = venv_bin()
    api_key = secrets.token_hex(16)
    compose = Compose(tmp_path, {"KMVIPE_API_KEY": api_key})
    (tmp_path / "home").mkdir()
    base = base_env(bin_dir, tmp_path / "home")
    config = make_secrets(bin_dir, base, compose, tmp_path, (*CAMERAS, JUNK))
    for volume in compose.volumes.values():
        volume.mkdir(parents=True)
    port = int(free_tcp_endpoint().rsplit(":", 1)[1])
    router, gateway_port = f"tls/localhost:{port}", int(free_tcp_endpoint().rsplit(":", 1)[1])
    url = f"http://127.0.0.1:{gateway_port}"
    entrypoint, image_env = dockerfile_image()
    assert entrypoint == ["kmvipe"], entrypoint
    procs, junk = Processes(tmp_path / "logs"), None
    try:
        start_router(procs, bin_dir, base, config, router_changes(compose, config, port), tmp_path)
        for name in SERVICES:
            command = compose.services[name]["command"]
            assert command == ["service", name], command
            env = service_env(compose, name, base, image_env, router, gateway_port, SPEC)
            procs.start(name, [str(bin_dir / entrypoint[0]), *command], env, tmp_path / "home")

        def ready() -> bool:
            procs.check_running()
            try:
                health = httpx.get(f"{url}/v1/health", timeout=5).json()
            except httpx.HTTPError:
                return False
            return all(health["services"].get(s, {}).get("alive") for s in SERVICES)

        wait_until(ready, READY_S, "every service alive at the gateway's /v1/health", poll=0.5)
        check_the_key(url, api_key)
        junk = Junk(router, compose.secret_dir)
        began = time.monotonic()
        for stream in CAMERAS:
            procs.start(f"publish-{stream}", [str(bin_dir / "kmvipe"), "publish", SPEC, "--stream", stream,
                                              "--pacing", "lossless", "--connect", router],
                        edge_env(base, compose.secret_dir, stream), tmp_path / "home")
        with httpx.Client(base_url=url, headers={"X-API-Key": api_key}, timeout=15) as http:
            watch = Watch(http)

            def finished() -> bool:
                procs.check_running(*SERVICES)
                return watch.poll()

            wait_until(finished, FINISH_BOUND_S, f"every frame posed and a map for each of {CAMERAS}", poll=0.5)
            took = {s: round(watch.done_at[s] - began, 1) for s in CAMERAS}
            print(f"posed and mapped, s after the publishers started: {took}; maps: {watch.maps}")
            # junk was served beside them (the mapstore answers for it), but nothing of it got through
            assert watch.maps.get(JUNK) is not None, "the junk stream's announcement never reached the mapstore"
            assert not watch.posed[JUNK] and watch.maps[JUNK]["keyframes"] == 0, watch.maps[JUNK]
            assert http.get(f"/v1/streams/{JUNK}/trajectory").status_code == 404
        # the garbage did reach the junk stream's worker (else it proved nothing): the one place that says so
        assert f'"key": "{keys.topic(JUNK, keys.FRAME)}"' in procs.log("features"), "junk never reached features"
        for name in SERVICES:
            assert "Traceback" not in procs.log(name), f"{name}:\n{procs.log(name)[-3000:]}"
    except BaseException:
        procs.dump()
        raise
    finally:
        if junk is not None:
            junk.close()
        procs.stop()
