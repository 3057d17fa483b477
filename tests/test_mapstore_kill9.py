"""Kill -9 the real mapstore process mid-stream over a real Zenoh session, restart it, finish the stream: every
keyframe it acknowledged survived, and the final map equals an uninterrupted run's.

"Acknowledged" here is what the code guarantees: ``MapState`` commits a keyframe to SQLite before applying it
to the in-memory map, and the ``map/stats`` queryable reports that map (``keyframes`` = keyframes held,
``seq`` = map revision, which every applied keyframe or graph advances). So a keyframe counted by ``stats``
is on disk. The test plays upstream with at-least-once delivery: it publishes one message, waits for the
revision to move (the acknowledgement), and after a restart resends everything not acknowledged — the
message that was in flight when the process was killed included (re-applying it is idempotent).
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from services.common import keys
from services.common.bus import Bus
from services.common.config import BusSettings
from services.common.errors import ServiceTimeout
from services.common.schema import Eos, Keyframe, MapStats, Message, PcaBasis, decode
from services.mapstore.config import MapstoreSettings
from services.mapstore.state import MapState
from tests.conftest import REPO, wait_until
from tests.test_mapstore_service import STREAM, stream_messages

N_KEYFRAMES = 8
KILL_AFTER_KEYFRAMES = 3  # acknowledged keyframes before the kill
UP_TIMEOUT_S = 60.0
ACK_TIMEOUT_S = 30.0


def start_mapstore(endpoint: str, db: Path) -> subprocess.Popen:
    env = {**os.environ, "KMVIPE_BUS_MODE": "peer", "KMVIPE_BUS_CONNECT": json.dumps([endpoint]),
           "KMVIPE_BUS_LISTEN": "[]", "KMVIPE_MAPSTORE_STREAM": STREAM, "KMVIPE_MAPSTORE_DB_PATH": str(db),
           "KMVIPE_MAPSTORE_DEVICE": "cpu", "PYTHONUNBUFFERED": "1"}
    return subprocess.Popen([sys.executable, "-m", "services.mapstore"], cwd=REPO, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def stats(bus: Bus) -> MapStats | None:
    try:
        return decode(bus.request(keys.map_key(STREAM, "stats"), timeout=1.0, service="mapstore"), MapStats)
    except (ServiceTimeout, RuntimeError):
        return None


class Upstream:
    """Publishes the stream in order over the bus, one acknowledged message at a time."""

    def __init__(self, bus: Bus, messages: list[Message]):
        self.bus, self.messages = bus, messages
        self.next = 0  # index of the first message not yet acknowledged
        self.acked_keyframes: list[int] = []

    def wait_up(self, proc: subprocess.Popen) -> MapStats:
        wait_until(lambda: stats(self.bus) is not None or proc.poll() is not None, UP_TIMEOUT_S, "mapstore up")
        assert proc.poll() is None, proc.stderr.read()
        return stats(self.bus)

    def publish(self, msg: Message) -> None:
        self.bus.publish(keys.topic(STREAM, msg.KIND), msg)  # every kind here travels on the key of its name

    def send_acked(self, until_keyframes: int | None = None) -> None:
        """Send messages (each waiting for its acknowledgement) until ``until_keyframes`` are acknowledged and the
        next message is a keyframe, or up to (not including) the final EOS."""
        while self.next < len(self.messages) - 1:
            if (until_keyframes is not None and len(self.acked_keyframes) >= until_keyframes
                    and isinstance(self.messages[self.next], Keyframe)):
                return
            msg = self.messages[self.next]
            before = stats(self.bus)
            self.publish(msg)
            if isinstance(msg, PcaBasis):
                wait_until(lambda: getattr(stats(self.bus), "pca_version", -1) == msg.version, ACK_TIMEOUT_S, "basis")
            else:
                wait_until(lambda: getattr(stats(self.bus), "seq", -1) > before.seq, ACK_TIMEOUT_S, f"ack of {msg.KIND} {msg.seq}")
            if isinstance(msg, Keyframe):
                self.acked_keyframes.append(msg.seq)
            self.next += 1


def finish(upstream: Upstream, bus_inbox) -> Eos:
    """Send the final EOS and wait for the mapstore to forward its own (it exports and closes the stream)."""
    eos = upstream.messages[-1]
    upstream.publish(eos)
    deadline = time.monotonic() + ACK_TIMEOUT_S
    while time.monotonic() < deadline:
        got = bus_inbox.get(1.0)
        if got is not None and got.msg.stage == "mapstore":
            return got.msg
    pytest.fail("the mapstore did not forward the end of stream")


def fused_map(db: Path):
    state = MapState(MapstoreSettings(stream=STREAM, db_path=str(db), device="cpu"))
    try:
        return state.map.fused(), set(state.map.contents)
    finally:
        state.close()


def stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def run_stream(endpoint: str, db: Path, kill: bool) -> tuple[list[int], set[int] | None]:
    """Stream everything to a real mapstore process; with ``kill``, SIGKILL it mid-stream and restart it.
    Returns (acknowledged keyframes before the kill, keyframes found on disk right after the kill)."""
    messages = stream_messages(N_KEYFRAMES)
    with Bus(BusSettings(mode="peer", listen=[endpoint]), "ba", "upstream") as bus:
        eos_inbox = bus.inbox({keys.topic(STREAM, keys.EOS): [Eos]})
        upstream = Upstream(bus, messages)
        proc = start_mapstore(endpoint, db)
        acked, on_disk = [], None
        try:
            upstream.wait_up(proc)
            if kill:
                upstream.send_acked(until_keyframes=KILL_AFTER_KEYFRAMES)
                acked = list(upstream.acked_keyframes)
                upstream.publish(messages[upstream.next])  # in flight when the process dies
                os.kill(proc.pid, signal.SIGKILL)
                proc.wait(timeout=30)
                _, on_disk = fused_map(db)
                proc = start_mapstore(endpoint, db)
                restarted = upstream.wait_up(proc)
                assert restarted.keyframes >= len(acked) and restarted.pca_version == 1
            upstream.send_acked()
            final_eos = finish(upstream, eos_inbox)
            assert final_eos.count == N_KEYFRAMES
        finally:
            stop(proc)
    return acked, on_disk


@pytest.mark.slow
def test_kill9_over_zenoh_keeps_acknowledged_keyframes_and_ends_with_the_uninterrupted_map(tmp_path, unix_endpoint):
    ref_db, crash_db = tmp_path / "ref.db", tmp_path / "crash.db"
    run_stream(unix_endpoint, ref_db, kill=False)
    acked, on_disk = run_stream(unix_endpoint, crash_db, kill=True)

    assert len(acked) == KILL_AFTER_KEYFRAMES
    assert set(acked) <= on_disk, f"acknowledged {acked}, on disk after kill -9 only {sorted(on_disk)}"
    expect, expect_kfs = fused_map(ref_db)
    final, final_kfs = fused_map(crash_db)
    assert final_kfs == expect_kfs and len(expect_kfs) == N_KEYFRAMES
    assert len(expect.keys) > 100
    order_e, order_f = np.argsort(expect.keys), np.argsort(final.keys)
    np.testing.assert_array_equal(final.keys[order_f], expect.keys[order_e])
    np.testing.assert_allclose(final.xyz[order_f], expect.xyz[order_e], rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(final.codes[order_f].astype(np.float32), expect.codes[order_e].astype(np.float32),
                               atol=1e-3)
