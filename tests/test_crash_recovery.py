"""Crash safety (issue 15): kill -9 of a service mid-stream and a restart as compose's ``restart: unless-stopped``
does. A restarted ba resumes from its checkpoint in the same world frame (features sends it again what came after
the checkpoint); a restarted gateway answers the whole trajectory from the mapstore's record of it. Either way
every frame of the lossless stream is posed, checked over HTTP through the gateway. Real processes on a loopback
router, the synthetic world's oracle backbone in place of DINO."""
from __future__ import annotations

import sqlite3
import subprocess
import threading

import httpx
import numpy as np
import pytest

from services.common import keys
from services.common.bus import Bus
from services.common.config import BusSettings
from services.common.schema import Eos, Keyframe, Poses
from services.evaluation.ate import absolute_trajectory_error
from services.evaluation.trajectory_io import Trajectory
from services.ingest.sources import open_source
from services.runner.children import free_tcp_endpoint
from tests.conftest import wait_until
from tests.helpers.processes import client_env, start, start_services, stop

FRAMES = 60
SPEC = f"synth:frames={FRAMES},width=256,height=192"


@pytest.mark.slow
@pytest.mark.timeout(600)
# features and the gateway share a run: the one is killed mid-stream, the other after the stream has ended; ba and
# the mapstore die together, as on a machine that lost both (each restarts from its own record: checkpoint, db)
@pytest.mark.parametrize("case", ["features+query_api", "ba+mapstore", "ba+mapstore-after-its-source-ended"])
def test_a_service_killed_mid_stream_loses_no_pose_and_keeps_one_world_frame(case, tmp_path, tcp_endpoint):
    victims = case.split("-")[0].split("+")
    port = int(free_tcp_endpoint().rsplit(":", 1)[1])
    env = client_env(tcp_endpoint, SPEC, tmp_path / "maps", KMVIPE_BA_CHECKPOINT_DIR=str(tmp_path / "ba"),
                     KMVIPE_BA_CHECKPOINT_PERIOD_S="0.5", KMVIPE_QUERY_PORT=str(port), KMVIPE_QUERY_HOST="127.0.0.1",
                     # slow mapping down a little so the kill lands mid-stream on a fast machine too
                     KMVIPE_BA_MAPPING_MIN_SECONDS="0.3")
    if case.endswith("after-its-source-ended"):  # ingest may run far ahead of ba: it ends (its token goes) first
        env["KMVIPE_FEATURES_DOWNSTREAM_FRAMES"] = "1000"
        env["KMVIPE_BA_MAPPING_MIN_SECONDS"] = "1.0"  # and ba far behind it
    mapped: set[int] = set()
    features_eos: list[Eos] = []
    ended = threading.Event()

    def on_pose(delivery) -> None:
        if not delivery.msg.tracked:
            mapped.update(int(s) for s in delivery.msg.frame_seqs)

    stage_eos: list[Eos] = []
    keyframes_sent: set[int] = set()

    def on_eos(delivery) -> None:
        stage_eos.append(delivery.msg)
        if delivery.msg.stage == "features":
            features_eos.append(delivery.msg)
        if delivery.msg.stage == "mapstore":
            ended.set()

    procs: list[subprocess.Popen] = []
    logs = tmp_path / "logs"
    logs.mkdir()
    with Bus(BusSettings(mode="router", listen=[tcp_endpoint]), "test") as bus:
        bus.subscribe(keys.topic("cam1", keys.POSE), on_pose, [Poses])
        bus.subscribe(keys.topic("cam1", keys.EOS), on_eos, [Eos])
        bus.subscribe(keys.topic("cam1", keys.KEYFRAME), lambda d: keyframes_sent.add(d.msg.seq), [Keyframe])
        try:
            services = start_services(("features", "ba", "mapstore", "query_api"), env, logs, bus)
            procs.extend(services.values())
            publisher = start(["publish", SPEC, "--stream", "cam1", "--pacing", "lossless", "--connect",
                               tcp_endpoint], env, logs / "publish.log")
            procs.append(publisher)
            checkpoints = tmp_path / "ba"
            wait_until(lambda: len(mapped) >= 20 and any(checkpoints.glob("cam1.*.ckpt")), 240,
                       "ba mapped 20 frames and wrote a checkpoint")
            if case.endswith("after-its-source-ended"):  # restarted, it finds no source: it resumes its own work
                wait_until(lambda: publisher.poll() is not None, 120, "the publisher streamed every frame and ended")
            assert not (ended.is_set() or any(e.stage == "ba" for e in stage_eos)), "the kill must land mid-stream"
            mid_stream = [v for v in victims if v != "query_api"]
            for victim in mid_stream:
                _kill_and_restart(services, victim, env, logs, procs, bus)
            assert ended.wait(300), (logs / f"{mid_stream[0]}.log").read_text()[-3000:]
            if "query_api" in victims:  # after the stream: a gateway that kept poses in memory only has none now
                _kill_and_restart(services, "query_api", env, logs, procs, bus)
            with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=15) as http:
                wait_until(lambda: _http_up(http), 60, "the gateway answers")
                answer = http.get("/v1/streams/cam1/trajectory")
                streams = http.get("/v1/streams").json()["streams"]
        finally:
            stop(procs)
    if "ba" in victims:
        restarted = (logs / "ba-restarted.log").read_text()
        assert "resumed from checkpoint" in restarted, restarted[-3000:]
    assert answer.status_code == 200, answer.text
    frames = answer.json()["frames"]
    assert [f["seq"] for f in frames] == list(range(FRAMES))  # every frame posed, over HTTP
    world = open_source(SPEC).world
    poses = np.array([f["world_from_cam"] for f in frames])
    ate = absolute_trajectory_error(Trajectory(np.arange(FRAMES, dtype=float), world.poses[:FRAMES]),
                                    Trajectory(np.arange(FRAMES, dtype=float), poses), align="sim3")
    # one world frame: a ba that started afresh would put the frames after the kill at a second identity
    assert ate.rmse < 0.01, ate.rmse
    # every keyframe features acknowledged is in the map
    with sqlite3.connect(tmp_path / "maps" / "cam1.db") as db:
        stored = {row[0] for row in db.execute("SELECT kf_id FROM keyframes")}
    assert features_eos and stored == keyframes_sent, (sorted(keyframes_sent - stored), sorted(stored - keyframes_sent))
    assert [s for s in streams if s["name"] == "cam1"][0]["session"]
    for name in {"features", "mapstore", "query_api", "ba"} - set(victims):
        text = (logs / f"{name}.log").read_text()
        assert "Traceback" not in text, text[-3000:]


def _kill_and_restart(services: dict, victim: str, env: dict, logs, procs: list, bus: Bus) -> None:
    services[victim].kill()  # kill -9
    services[victim].wait()
    procs.append(start(["service", victim], env, logs / f"{victim}-restarted.log"))  # restart: unless-stopped
    wait_until(lambda: victim in bus.alive(timeout=0.5), 60, f"{victim} back")


def _http_up(http: httpx.Client) -> bool:
    try:
        return http.get("/v1/health").status_code == 200
    except httpx.HTTPError:
        return False
