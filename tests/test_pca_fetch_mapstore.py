"""Mapstore over real Zenoh: basis v2 never comes on the ``pca`` topic, yet the codes coded with it are fused,
because the mapstore fetched v2 from the real features ``pca`` queryable (after features came up: the first
request failed, was counted, and was retried). The final map equals one built from every message, v2 included.

Keyframes (geometry first), their codes and bases are the real features outputs (tests/test_pca_fetch_features.py);
ba's graphs are the synthetic world's exact poses and depth. The test plays upstream: one message at a time, each
waited for. Codes whose basis is unknown wait for it (the keyframe is fused for geometry meanwhile); stored before
a restart, they hold their keyframe until the basis is fetched.
"""
from __future__ import annotations

import dataclasses
import threading
from pathlib import Path

import numpy as np

from services.common import keys
from services.common.bus import Bus
from services.common.config import BusSettings
from services.common.pca_fetch import BasisFetch, FetchParams
from services.common.schema import Graph, Keyframe, KeyframeCodes, Message, PcaBasis
from services.mapstore import service as mapstore
from services.mapstore.config import MapstoreSettings
from services.mapstore.state import MapState
from tests.conftest import wait_until
from tests.test_pca_fetch_features import HEIGHT, WIDTH, FeaturesRun, features_run, serve
from tests.test_pca_versions_mapstore import assert_same_map

STREAM = "pfm"
MISSED = 2  # the basis version never published on the topic
ACK_S = 20.0


def with_graphs(run: FeaturesRun) -> list[Message]:
    """features' bases, keyframes and codes, each keyframe followed by ba's graph: exact poses of every keyframe so
    far and the exact disparity of the new one on the 1/8 grid (cell centres, docs/CONVENTIONS.md)."""
    out: list[Message] = []
    seqs: list[int] = []
    grid = slice(3, None, 8)
    for msg in run.outputs:
        if isinstance(msg, (PcaBasis, KeyframeCodes)):
            out.append(msg)
        if not isinstance(msg, Keyframe):
            continue
        seqs.append(msg.seq)
        f = run.world.render(msg.seq)
        poses = np.stack([run.world.render(s).world_from_cam for s in seqs])
        disp = (1.0 / f.depth[grid, grid])[None].astype(np.float32)
        out += [msg, Graph(msg.stream, msg.seq, msg.t_ns, kf_seqs=np.array(seqs), poses=poses,
                           intrinsics=f.intrinsics, width=WIDTH, height=HEIGHT, updated_seqs=np.array([msg.seq]),
                           disparities=disp)]
    return out


def settings(path: Path) -> MapstoreSettings:
    return MapstoreSettings(stream=STREAM, db_path=str(path / "{stream}.db"), device="cpu")


def applied(state: MapState, msg: Message) -> bool:
    """Whether the mapstore has taken ``msg`` in (read under its lock: its loop runs on another thread)."""
    with state.lock:
        if isinstance(msg, PcaBasis):
            return msg.version in state.bases
        if isinstance(msg, Keyframe):
            return msg.seq in state.map.contents
        if isinstance(msg, KeyframeCodes):
            return msg.seq in state.waiting_codes or state.has_codes(msg.seq)
        return int(msg.updated_seqs[0]) in state.map.poses


def waiting(state: MapState) -> list[int]:
    """Keyframes whose codes wait for their basis (or their keyframe)."""
    with state.lock:
        return sorted(state.waiting_codes)


def held(state: MapState) -> list[int]:
    with state.lock:
        return state.map.held


def test_codes_whose_basis_never_came_are_fused_with_the_basis_fetched_from_features(tmp_path, unix_endpoint):
    run = features_run(STREAM)
    msgs = [m for m in with_graphs(run) if not (isinstance(m, PcaBasis) and m.version == MISSED)]
    first_missed = next(i for i, m in enumerate(msgs) if isinstance(m, KeyframeCodes) and m.pca_version == MISSED)
    cfg = settings(tmp_path / "live")
    state = MapState(cfg)
    fetch = BasisFetch(FetchParams(retry_s=0.5))
    stop = threading.Event()
    with Bus(BusSettings(listen=[unix_endpoint]), "mapstore") as mbus, \
            Bus(BusSettings(connect=[unix_endpoint]), "features") as fbus, \
            Bus(BusSettings(connect=[unix_endpoint]), "tester") as bus:
        worker = threading.Thread(target=mapstore.run, args=(cfg, mbus, stop, state, fetch), daemon=True)
        worker.start()
        wait_until(lambda: "mapstore" in bus.alive(timeout=0.2), 10, "the mapstore to be alive")

        def send(msg: Message) -> None:
            bus.publish(keys.topic(STREAM, msg.KIND), msg)
            wait_until(lambda: applied(state, msg), ACK_S, f"the mapstore to apply {msg.KIND} {msg.seq}")

        for msg in msgs[: first_missed + 1]:  # up to the first codes of the missed version
            send(msg)
        missed_seq = msgs[first_missed].seq
        # features is not serving yet: the request fails, is counted, and the codes wait (the geometry is fused)
        wait_until(lambda: fetch.failures["timeout"] >= 1, ACK_S, "a failed request for the missed basis")
        assert missed_seq in waiting(state) and not held(state) and worker.is_alive()
        features_worker, features_stop = serve(run, fbus)
        wait_until(lambda: MISSED in state.bases and state.has_codes(missed_seq), ACK_S,
                   "the missed basis fetched from features on a retry")
        for msg in msgs[first_missed + 1:]:
            send(msg)
        # codes of a version features never published: an error reply, counted; they wait, and the service lives
        stray = dataclasses.replace(msgs[first_missed], seq=1000, pca_version=99)
        send(stray)
        wait_until(lambda: fetch.failures["error_reply"] >= 1, ACK_S, "the refusal of version 99")
        assert worker.is_alive()
        stop.set()
        features_stop.set()
        worker.join(10)
        features_worker.join(10)
    assert fetch.fetched == {MISSED: 1}  # asked once it could be answered, and only for the version it missed
    assert waiting(state) == [stray.seq] and not held(state) and state.map.code_version == max(run.state.bases)
    sent = next(m for m in run.outputs if isinstance(m, PcaBasis) and m.version == MISSED)
    np.testing.assert_array_equal(state.bases[MISSED].components, sent.components)
    np.testing.assert_array_equal(state.store.load().bases[MISSED].mean, sent.mean)  # committed like a message

    reference = MapState(settings(tmp_path / "reference"))
    for msg in with_graphs(run):  # every message, v2 included, straight through the handlers
        mapstore.handle(reference, msg, reference.cfg)
    assert not reference.map.held and not reference.waiting_codes
    assert reference.map.code_version == state.map.code_version
    assert_same_map(state.map, reference.map)
    state.close()
    reference.close()


def test_a_restarted_mapstore_fetches_the_bases_its_stored_keyframes_wait_for(tmp_path, unix_endpoint):
    run = features_run(STREAM)
    cfg = settings(tmp_path)
    first = MapState(cfg)  # the run before the restart: v2 never came, its codes are stored and wait for it
    for msg in with_graphs(run):
        if not (isinstance(msg, PcaBasis) and msg.version == MISSED):
            mapstore.handle(first, msg, cfg)
    missed = [m.seq for m in run.outputs if isinstance(m, KeyframeCodes) and m.pca_version == MISSED]
    assert missed and waiting(first) == missed and not held(first)
    first.close()
    state = MapState(cfg)  # restart: reloads the keyframe with its codes from SQLite, held for the basis
    assert held(state) == missed
    fetch = BasisFetch()
    stop = threading.Event()
    with Bus(BusSettings(listen=[unix_endpoint]), "features") as fbus, \
            Bus(BusSettings(connect=[unix_endpoint]), "mapstore") as mbus:
        features_worker, features_stop = serve(run, fbus)
        wait_until(lambda: "features" in mbus.alive(timeout=0.2), 10, "features to be alive")
        worker = threading.Thread(target=mapstore.run, args=(cfg, mbus, stop, state, fetch), daemon=True)
        worker.start()
        wait_until(lambda: not held(state), ACK_S, "the held keyframe freed by the fetched basis")
        stop.set()
        features_stop.set()
        worker.join(10)
        features_worker.join(10)
    assert fetch.fetched == {MISSED: 1} and not fetch.failures
    reference = MapState(settings(tmp_path / "reference"))
    for msg in with_graphs(run):
        mapstore.handle(reference, msg, reference.cfg)
    assert_same_map(state.map, reference.map)
    state.close()
    reference.close()
