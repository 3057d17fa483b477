"""10,000 bad payloads on every key a running service subscribes to: it stays alive, counts them, and still
processes a valid message afterwards. Real processes, real Zenoh (unix socket, no scouting)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import pytest

from services.common import keys
from services.common.bus import Bus
from services.common.config import BusSettings
from services.common.schema import Credit, Eos, Frame
from tests.conftest import REPO, wait_until
from tests.helpers.fuzz import bad_payloads

N_BAD = 10_000


def _start_service(name: str, endpoint: str, env: dict) -> subprocess.Popen:
    full_env = {**os.environ, "KMVIPE_BUS_MODE": "peer", "KMVIPE_BUS_CONNECT": json.dumps([endpoint]), **env}
    return subprocess.Popen([sys.executable, "-m", f"services.{name}"], cwd=REPO, env=full_env,
                            stderr=subprocess.PIPE, text=True)


@pytest.mark.slow
def test_ingest_survives_garbage_on_credit_and_still_streams(unix_endpoint):
    stream = "fuzz"
    with Bus(BusSettings(mode="peer", listen=[unix_endpoint]), "features", "fuzzer") as bus:
        frames = bus.inbox({keys.topic(stream, keys.FRAME): [Frame], keys.topic(stream, keys.EOS): [Eos]})
        ingest = _start_service("ingest", unix_endpoint, {
            "KMVIPE_INGEST_SOURCE": "synth:frames=3,width=64,height=48", "KMVIPE_INGEST_STREAM": stream,
            "KMVIPE_INGEST_PACING": "lossless",
        })
        try:
            wait_until(lambda: "ingest" in bus.alive(timeout=0.2), 60, "ingest to come up")
            credit_key = keys.topic(stream, keys.CREDIT)
            # bases for truncation/bit flips: other kinds on this key (a flipped *credit* could still be a valid
            # credit, which is not garbage); truncated credits are covered by the truncated Eos/Frame maps
            valid = [Eos(stream, 5, 0, stage="ingest").encode(),
                     Frame(stream, 0, 0, 2, 1, jpeg=b"\xff\xd8").encode()]
            for payload in bad_payloads(valid, N_BAD):
                bus.put(credit_key, payload)
            time.sleep(0.5)  # the garbage is still draining through the ingest's session
            assert ingest.poll() is None, "ingest died of bad payloads"
            assert frames.get(timeout=0.1) is None, "garbage must not have granted credit"
            bus.publish(credit_key, Credit(stream, 10, time.time_ns(), consumer="fuzzer"))
            got = [frames.get(timeout=30) for _ in range(4)]
        finally:
            ingest.terminate()
            _, log = ingest.communicate(timeout=30)
    assert [type(d.msg) for d in got] == [Frame, Frame, Frame, Eos], log
    assert [d.msg.seq for d in got[:3]] == [0, 1, 2]
    assert "dropped bad payload" in log  # counted and logged once per kind, not once per payload
    assert log.count("dropped bad payload") < 10
