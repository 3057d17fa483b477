"""Many cameras per deployment (issue 14): features, ba and mapstore started once, without a stream setting, serve
every stream a source announces, each with its own state and map; a source that sends garbage does not hold the
others up. Real processes on a loopback router, the synthetic world's oracle backbone in place of DINO."""
from __future__ import annotations

import sqlite3
import subprocess
import threading
import time

import pytest

from services.common import keys
from services.common.bus import Bus
from services.common.config import BusSettings
from services.common.schema import Eos, Poses
from tests.conftest import wait_until
from tests.helpers.processes import client_env, start, start_services, stop

SPEC = "synth:frames=24,width=256,height=192"
STREAMS = ("cam1", "cam2", "cam3")


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_three_cameras_each_get_every_frame_posed_and_their_own_map(tmp_path, tcp_endpoint):
    env = client_env(tcp_endpoint, SPEC, tmp_path / "maps", KMVIPE_STREAMS_IDLE_S="5")
    poses: dict[str, set[int]] = {s: set() for s in STREAMS}
    ended: dict[str, float] = {}
    lock = threading.Lock()

    def on_pose(delivery) -> None:
        with lock:
            poses.setdefault(delivery.msg.stream, set()).update(int(s) for s in delivery.msg.frame_seqs)

    def on_eos(delivery) -> None:
        if delivery.msg.stage == "mapstore":
            with lock:
                ended[delivery.msg.stream] = time.monotonic()

    procs: list[subprocess.Popen] = []
    with Bus(BusSettings(mode="router", listen=[tcp_endpoint]), "test") as bus:
        bus.subscribe(keys.topic("*", keys.POSE), on_pose, [Poses])
        bus.subscribe(keys.topic("*", keys.EOS), on_eos, [Eos])
        try:
            procs.extend(start_services(("features", "ba", "mapstore"), env, tmp_path, bus).values())
            # a fourth source announces itself and sends garbage on its frame key
            garbage = bus.announce("junk")
            for _ in range(50):
                bus.put(keys.topic("junk", keys.FRAME), b"\x93not a frame")
            began = time.monotonic()
            for stream in STREAMS:
                procs.append(start(["publish", SPEC, "--stream", stream, "--pacing", "lossless", "--connect",
                                     tcp_endpoint], env, tmp_path / f"publish-{stream}.log"))
            wait_until(lambda: set(STREAMS) <= set(ended), 420, "every stream's end of stream")
            garbage.undeclare()
        finally:
            stop(procs)
    logs = {p.name: p.read_text() for p in tmp_path.glob("*.log")}
    for stream in STREAMS:
        assert poses[stream] >= set(range(24)), (stream, sorted(poses[stream]), logs.get("ba.log", "")[-2000:])
        with sqlite3.connect(tmp_path / "maps" / f"{stream}.db") as db:  # a map of its own
            assert db.execute("select count(*) from keyframes").fetchone()[0] >= 3
    assert not poses.get("junk")  # its garbage was counted and dropped, it never reached a stage's state
    print(f"3 streams of 24 frames: every frame posed, last end of stream {max(ended.values()) - began:.1f} s after "
          "the publishers started")
    for name in ("features", "ba", "mapstore"):
        assert "Traceback" not in logs[f"{name}.log"], logs[f"{name}.log"][-3000:]
