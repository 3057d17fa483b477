"""Mapstore over real Zenoh: basis v2 never comes on the ``pca`` topic, yet the keyframe coded with it is fused,
because the mapstore fetched v2 from the real features ``pca`` queryable (after features came up: the first
request failed, was counted, and was retried). The final map equals one built from every message, v2 included.

Keyframes and bases are the real features outputs (tests/test_pca_fetch_features.py); ba's graphs are the
synthetic world's exact poses and depth. The test plays upstream: one message at a time, each waited for.
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
from services.common.schema import Graph, Keyframe, Message, PcaBasis
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
    """features' bases and keyframes, each keyframe followed by ba's graph: exact poses of every keyframe so far
    and the exact disparity of the new one on the 1/8 grid (cell centres, docs/CONVENTIONS.md)."""
    out: list[Message] = []
    seqs: list[int] = []
    grid = slice(3, None, 8)
    for msg in run.outputs:
        if isinstance(msg, PcaBasis):
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
        return int(msg.updated_seqs[0]) in state.map.poses


def held(state: MapState) -> list[int]:
    with state.lock:
        return state.map.held


def test_a_keyframe_whose_basis_never_came_is_fused_with_the_basis_fetched_from_features(tmp_path, unix_endpoint):
    run = features_run(STREAM)
    msgs = [m for m in with_graphs(run) if not (isinstance(m, PcaBasis) and m.version == MISSED)]
    first_missed = next(i for i, m in enumerate(msgs) if isinstance(m, Keyframe) and m.pca_version == MISSED)
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

        for msg in msgs[: first_missed + 2]:  # up to the first keyframe of the missed version and its graph
            send(msg)
        missed_seq = msgs[first_missed].seq
        # features is not serving yet: the request fails, is counted, and the keyframe stays held
        wait_until(lambda: fetch.failures["timeout"] >= 1, ACK_S, "a failed request for the missed basis")
        assert missed_seq in held(state) and worker.is_alive()
        features_worker, features_stop = serve(run, fbus)
        wait_until(lambda: MISSED in state.bases and missed_seq not in held(state), ACK_S,
                   "the missed basis fetched from features on a retry")
        for msg in msgs[first_missed + 2:]:
            send(msg)
        # a keyframe of a version features never published: an error reply, counted; held, and the service lives
        stray = dataclasses.replace(msgs[first_missed], seq=1000, pca_version=99)
        send(stray)
        wait_until(lambda: fetch.failures["error_reply"] >= 1, ACK_S, "the refusal of version 99")
        assert worker.is_alive()
        stop.set()
        features_stop.set()
        worker.join(10)
        features_worker.join(10)
    assert fetch.fetched == {MISSED: 1}  # asked once it could be answered, and only for the version it missed
    assert held(state) == [stray.seq] and state.map.code_version == max(run.state.bases)
    sent = next(m for m in run.outputs if isinstance(m, PcaBasis) and m.version == MISSED)
    np.testing.assert_array_equal(state.bases[MISSED].components, sent.components)
    np.testing.assert_array_equal(state.store.load().bases[MISSED].mean, sent.mean)  # committed like a message

    reference = MapState(settings(tmp_path / "reference"))
    for msg in with_graphs(run):  # every message, v2 included, straight through the handlers
        mapstore.handle(reference, msg, reference.cfg)
    assert not reference.map.held and reference.map.code_version == state.map.code_version
    assert_same_map(state.map, reference.map)
    state.close()
    reference.close()


def test_a_restarted_mapstore_fetches_the_bases_its_stored_keyframes_wait_for(tmp_path, unix_endpoint):
    run = features_run(STREAM)
    cfg = settings(tmp_path)
    first = MapState(cfg)  # the run before the restart: v2 never came, its keyframe is stored and held
    for msg in with_graphs(run):
        if not (isinstance(msg, PcaBasis) and msg.version == MISSED):
            mapstore.handle(first, msg, cfg)
    missed = [m.seq for m in run.outputs if isinstance(m, Keyframe) and m.pca_version == MISSED]
    assert held(first) == missed
    first.close()
    state = MapState(cfg)  # restart: reloads the held keyframe from SQLite; nothing more comes on the topics
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
