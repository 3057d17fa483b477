"""BA over real Zenoh: basis v2 never comes on the ``pca`` topic, yet the keyframe whose codes use it gets codes in the
graph, because ba fetched v2 from the real features ``pca`` queryable. Every code in the graph is then the exact
conversion (services/common/pca_codes.py) of what its keyframe carried into the newest version.

Keyframes and bases are the real features outputs (tests/test_pca_fetch_features.py); the test plays upstream,
one message at a time, each waited for.
"""
from __future__ import annotations

import threading

import torch

from services.ba import service as ba
from services.ba.settings import BaSettings
from services.common import keys
from services.common.bus import Bus
from services.common.config import BusSettings
from services.common.pca_codes import code_map, convert_codes
from services.common.schema import Keyframe, KeyframeCodes, PcaBasis
from tests.conftest import wait_until
from tests.test_pca_fetch_features import features_run, serve

STREAM = "pfb"
MISSED = 2  # the basis version never published on the topic
ACK_S = 30.0


def settings() -> BaSettings:
    # every keyframe stays in the graph (no sliding two-view window), so the one coded with the missed basis does
    return BaSettings(stream=STREAM, device="cpu", threads=1, init_min_flow=0.5, focal_after=3, iterations=2,
                      global_iterations=3, init_max_keyframes=100)


def _has_native_codes(state, seq: int) -> bool:
    g = state.frontend.graph
    return g is not None and seq in g.seqs and g.native_codes[g.index(seq)] is not None


def test_a_keyframe_whose_basis_never_came_gets_codes_from_the_basis_fetched_from_features(unix_endpoint):
    run = features_run(STREAM)
    msgs = [m for m in run.outputs
            if isinstance(m, (Keyframe, KeyframeCodes)) or (isinstance(m, PcaBasis) and m.version != MISSED)]
    missed_seq = next(m.seq for m in msgs if isinstance(m, KeyframeCodes) and m.pca_version == MISSED)
    cfg = settings()
    state = ba.build_state(cfg)
    stop = threading.Event()
    with Bus(BusSettings(listen=[unix_endpoint]), "ba") as ba_bus, \
            Bus(BusSettings(connect=[unix_endpoint]), "features") as fbus, \
            Bus(BusSettings(connect=[unix_endpoint]), "tester") as bus:
        features_worker, features_stop = serve(run, fbus)
        worker = threading.Thread(target=ba.run, args=(cfg, ba_bus, stop, state), daemon=True)
        worker.start()
        wait_until(lambda: {"ba", "features"} <= set(bus.alive(timeout=0.2)), 10, "ba and features to be alive")
        seen = 0
        for msg in msgs:
            bus.publish(keys.topic(STREAM, msg.KIND), msg)
            if isinstance(msg, Keyframe):
                seen += 1
                wait_until(lambda: state.keyframes_seen >= seen, ACK_S, f"ba to take keyframe {msg.seq}")
            elif isinstance(msg, KeyframeCodes):
                wait_until(lambda: _has_native_codes(state, msg.seq), ACK_S, f"ba to take the codes of {msg.seq}")
            else:
                wait_until(lambda: msg.version in state.bases, ACK_S, f"ba to take basis {msg.version}")
        wait_until(lambda: MISSED in state.bases, ACK_S, "ba to fetch the missed basis")
        stop.set()
        features_stop.set()
        worker.join(30)
        features_worker.join(10)
    assert not worker.is_alive()
    assert state.pca_fetch.fetched == {MISSED: 1} and not state.pca_fetch.failures
    newest = max(run.state.bases)
    assert state.pca_version == newest and sorted(state.bases) == list(range(1, newest + 1))
    g = state.frontend.graph
    assert missed_seq in g.seqs and len(g) >= 3
    sent = {m.version: m for m in run.outputs if isinstance(m, PcaBasis)}  # v2 as features published it
    for seq, codes, native in zip(g.seqs, g.codes, g.native_codes):
        assert codes is not None, f"keyframe {seq} (version {native.version}) left without codes"
        expect = convert_codes(native.codes, code_map(sent[native.version], sent[newest]))
        torch.testing.assert_close(codes, torch.from_numpy(expect), atol=1e-5, rtol=0)
