"""The mapstore live: a keyframe's geometry first (``Keyframe`` without codes), its codes later (``KeyframeCodes``).

The geometry is fused at once (points, colours, carving's depth evidence; no code sums) and answers queries as
absent; codes that come later — or before their keyframe, or before their basis — are committed and re-fused, and
the map ends the same as when every keyframe carried its codes. The end of stream waits for the codes (lossless)
unless the keyframes came from a real-time stream; a restart (clean or SIGKILL) keeps a codes-less keyframe and
codes committed later. Over real Zenoh: codes on ``kmvipe/<s>/codes`` and progress reports on
``kmvipe/<s>/progress``.
"""
from __future__ import annotations

import dataclasses
import os
import signal
import subprocess
import sys
import textwrap
import threading
from pathlib import Path

import numpy as np
import pytest

from services.common import keys
from services.common.bus import Bus
from services.common.config import BusSettings
from services.common.schema import (Credit, Eos, Graph, Keyframe, KeyframeCodes, MapQuery, MapStats, Message,
                                    PcaBasis as PcaMessage, decode)
from services.mapstore import service as mapstore
from services.mapstore.config import CarvingParams, MapParams
from services.mapstore.core.fusion import voxel_keys
from services.mapstore.core.map import KeyframeMap
from services.mapstore.service import handle, stream_complete
from services.mapstore.state import MapState
from tests.conftest import REPO, wait_until
from tests.test_mapstore_core import make_keyframe, pose
from tests.test_mapstore_service import STREAM, ask, settings, stream_messages

N_KF = 6
ACK_S = 20.0


def split(msg: Keyframe) -> tuple[Keyframe, KeyframeCodes]:
    """A keyframe as the live features sends it: geometry at once, codes in their own message."""
    geometry = dataclasses.replace(msg, codes=None, pca_version=-1)
    return geometry, KeyframeCodes(msg.stream, msg.seq, msg.t_ns, pca_version=msg.pca_version, codes=msg.codes)


def live_stream(n: int = N_KF, realtime: bool = False):
    """(basis, [geometry keyframes], [codes], [graphs], eos) of the synthetic stream, keyframes codes-less."""
    msgs = stream_messages(n)
    basis = next(m for m in msgs if isinstance(m, PcaMessage))
    pairs = [split(dataclasses.replace(m, realtime=realtime)) for m in msgs if isinstance(m, Keyframe)]
    graphs = [m for m in msgs if isinstance(m, Graph)]
    return basis, [g for g, _ in pairs], [c for _, c in pairs], graphs, msgs[-1]


def feed(state: MapState, msgs: list[Message]) -> list[tuple[str, Message]]:
    out = []
    for m in msgs:
        out += handle(state, m, state.cfg)
    return out


def whole_map(path: Path, n: int = N_KF, **kw) -> MapState:
    """The reference: every keyframe carries its codes (the path before codes had their own message)."""
    state = MapState(settings(path, **kw))
    feed(state, [m for m in stream_messages(n) if not isinstance(m, Eos)])
    return state


def assert_same_map(a: MapState, b: MapState, codes: bool = True) -> None:
    fa, fb = a.map.fused(), b.map.fused()
    assert len(fa.keys) > 100
    np.testing.assert_array_equal(fa.keys, fb.keys)
    np.testing.assert_allclose(fa.xyz, fb.xyz, rtol=1e-9, atol=1e-12)
    np.testing.assert_array_equal(fa.colours, fb.colours)
    if codes:
        np.testing.assert_allclose(fa.codes, fb.codes, atol=1e-5)
        np.testing.assert_allclose(fa.code_weight, fb.code_weight, rtol=1e-12)


def query(state: MapState, vectors: np.ndarray, top_k: int = 10):
    return ask(state, "query", request=MapQuery(STREAM, 1, 0, vectors=vectors.astype(np.float32), top_k=top_k,
                                                with_points=True))


def code_query(state: MapState, codes: KeyframeCodes) -> np.ndarray:
    """(1, D) backbone-space vector decoded from the code of one of the keyframe's map points."""
    cell = state.map.keyframe_points(codes.seq).cells[0]
    z = codes.codes.reshape(-1, codes.codes.shape[2])[cell].astype(np.float32)
    basis = state.basis()
    return (basis.mean + z @ basis.components)[None]


def test_core_geometry_only_keyframes_carry_no_code_weight_and_set_codes_completes_the_map():
    """KeyframeMap alone (unversioned): keyframes without codes — the first one included, so the grid starts
    without a code size — fuse like the others for geometry and not at all for codes; `set_codes` makes the map of
    keyframes that had their codes from the start."""
    rng = np.random.default_rng(0)
    params = MapParams(carving=CarvingParams(semantic=False))  # random codes: semantic carving would differ
    frames = [make_keyframe(rng, i) for i in range(5)]
    full, live = KeyframeMap(params), KeyframeMap(params)
    for i, (content, depth) in enumerate(frames):
        bare = dataclasses.replace(content, codes=None, pca_version=-1)
        for m, c in ((full, content), (live, content if i == 3 else bare)):
            m.add_content(c)
            m.set_depth(i, depth)
            m.set_pose(i, pose(0.1 * i, 0.02 * i))
    full.refresh(), live.refresh()
    a, b = full.fused(), live.fused()
    np.testing.assert_array_equal(a.keys, b.keys)
    np.testing.assert_allclose(a.xyz, b.xyz, atol=1e-12)
    assert live.without_codes == [0, 1, 2, 4] and live.keyframe_points(0).codes is None
    own = {int(k) for k in voxel_keys(np.floor(live.keyframe_points(3).xyz / live.voxel_size).astype(np.int64))}
    coded = b.code_weight > 0
    assert {int(k) for k in b.keys[coded]} == own and np.all(np.isnan(b.codes[~coded]))
    pts = live.keyframe_points(3)  # the coded voxels hold keyframe 3's codes alone
    for key in own:
        sel = voxel_keys(np.floor(pts.xyz / live.voxel_size).astype(np.int64)) == key
        expect = (pts.weight[sel, None] * pts.codes[sel].astype(np.float64)).sum(0) / pts.weight[sel].sum()
        np.testing.assert_allclose(b.codes[np.flatnonzero(b.keys == key)[0]], expect, rtol=1e-4, atol=1e-4)
    for i in (0, 1, 2, 4):
        live.set_codes(i, frames[i][0].codes, 1)
    assert live.refresh().refreshed == [0, 1, 2, 4]  # just them: their neighbours' consistency is unchanged
    b = live.fused()
    np.testing.assert_array_equal(a.keys, b.keys)
    np.testing.assert_allclose(a.codes, b.codes, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(b.code_weight, a.weight)
    live.add_content(dataclasses.replace(frames[2][0], codes=None, pca_version=-1))  # codes withdrawn: the code
    live.refresh()  # sums of voxels no other keyframe codes leave exactly (no rounding residue poses as a code)
    b = live.fused()
    np.testing.assert_array_equal(b.code_weight == 0, np.isnan(b.codes).any(axis=1))
    assert (b.code_weight == 0).any() and live.without_codes == [2]


def test_geometry_is_fused_at_once_and_codes_arriving_later_make_it_scorable(tmp_path):
    basis, geometry, codes, graphs, _ = live_stream()
    state = MapState(settings(tmp_path / "live"))
    feed(state, [basis] + [m for pair in zip(geometry, graphs) for m in pair])
    # (a) geometry at once: the same points as the full map without semantic carving, and no code anywhere
    assert_same_map(state, whole_map(tmp_path / "geometry", carve_semantic=False), codes=False)
    fused = state.map.fused()
    assert np.all(fused.code_weight == 0) and np.all(np.isnan(fused.codes))
    stats = ask(state, "stats")
    assert stats.keyframes == N_KF and stats.keyframes_without_codes == N_KF and stats.points == len(fused.keys)
    assert state.store.load().contents[geometry[0].seq].codes is None  # committed without codes
    # queries still answer: every point absent (not the PCA mean's score), no region, no top point
    answer = query(state, code_query(state, codes[0]))
    assert answer.n_points == stats.points and np.all(np.isnan(answer.all_scores))
    assert len(answer.point_score) == 0 and len(answer.region_score) == 0
    seg = ask(state, "segment", request=MapQuery(STREAM, 2, 0, vectors=code_query(state, codes[0]).astype(np.float32)))
    assert np.all(seg.label == -1) and len(seg.label) == stats.points

    # (b) the codes of one keyframe: its voxels become scorable, and a vector decoded from its codes ranks them
    feed(state, [codes[2]])
    fused = state.map.fused()
    coded = fused.code_weight > 0
    assert 0 < coded.sum() < len(coded) and ask(state, "stats").keyframes_without_codes == N_KF - 1
    assert state.store.load().contents[codes[2].seq].pca_version == codes[2].pca_version
    points = state.map.keyframe_points(codes[2].seq)
    own = np.unique(np.floor(points.xyz / state.map.voxel_size).astype(np.int64), axis=0)
    np.testing.assert_array_equal(np.sort(fused.ijk[coded], axis=0), np.sort(own, axis=0))  # its voxels only
    answer = query(state, code_query(state, codes[2]))
    np.testing.assert_array_equal(np.isnan(answer.all_scores[0]), ~coded)
    assert len(answer.point_score) == 10 and answer.point_score[0] > 0.95
    where = {tuple(p): i for i, p in enumerate(fused.xyz.astype(np.float32).tolist())}
    top = [where[tuple(p)] for p in answer.point_xyz.tolist()]
    assert np.all(coded[top]) and answer.point_score[0] == np.nanmax(answer.all_scores[0])

    # every keyframe's codes: the map of keyframes that carried their codes
    feed(state, codes)
    assert ask(state, "stats").keyframes_without_codes == 0 and not state.waiting_codes
    assert_same_map(state, whole_map(tmp_path / "whole"))


def test_codes_before_their_keyframe_or_their_basis_wait_and_give_the_same_map(tmp_path):
    basis, geometry, codes, graphs, _ = live_stream()
    reference = whole_map(tmp_path / "whole")
    early = MapState(settings(tmp_path / "early"))
    feed(early, [basis] + codes[:3])  # (c) codes before their keyframes (another key): held
    assert early.map.contents == {} and set(early.waiting_codes) == {c.seq for c in codes[:3]}
    feed(early, [m for pair in zip(geometry, graphs) for m in pair] + codes[3:])
    assert not early.waiting_codes and early.map.without_codes == []
    assert_same_map(early, reference)

    no_basis = MapState(settings(tmp_path / "no_basis"))
    feed(no_basis, [m for pair in zip(geometry, graphs) for m in pair] + codes)  # the basis is still on the way
    assert set(no_basis.waiting_codes) == {c.seq for c in codes} and no_basis.map.held == []
    assert len(no_basis.map.fused().keys) > 100  # the geometry is in meanwhile
    assert no_basis.store.load().contents[codes[0].seq].codes is not None  # the codes are committed
    feed(no_basis, [basis])
    assert not no_basis.waiting_codes and no_basis.map.without_codes == []
    assert_same_map(no_basis, reference)


def test_a_repeated_geometry_message_keeps_the_codes_and_old_keyframes_with_codes_still_work(tmp_path):
    basis, geometry, codes, graphs, _ = live_stream(3)
    state = MapState(settings(tmp_path / "a"))
    feed(state, [basis] + [m for pair in zip(geometry, graphs) for m in pair] + codes + [geometry[1]])
    assert state.map.without_codes == [] and state.store.load().contents[geometry[1].seq].codes is not None
    assert_same_map(state, whole_map(tmp_path / "whole", 3))


def test_the_end_of_stream_waits_for_the_codes_unless_the_stream_is_real_time(tmp_path):
    basis, geometry, codes, graphs, eos = live_stream()
    state = MapState(settings(tmp_path / "lossless"))
    assert feed(state, [basis] + [m for pair in zip(geometry, graphs) for m in pair] + [eos]) == []
    assert state.pending_eos is eos and not stream_complete(state)  # lossless: every keyframe gets codes
    feed(state, codes[:-1])
    assert not stream_complete(state)
    feed(state, codes[-1:])
    assert stream_complete(state)
    out = mapstore.finish_stream(state, eos, state.cfg)
    assert [(m.stage, m.count) for _, m in out] == [("mapstore", N_KF)]

    basis, geometry, codes, graphs, eos = live_stream(realtime=True)
    rt = MapState(settings(tmp_path / "realtime"))
    feed(rt, [basis] + [m for pair in zip(geometry, graphs) for m in pair] + codes[:2])
    out = feed(rt, [eos])  # real time: the backbone may have skipped the others' codes, nothing to wait for
    assert [(m.stage, m.count) for _, m in out] == [("mapstore", N_KF)]
    assert ask(rt, "stats").keyframes_without_codes == N_KF - 2


def test_a_codes_less_keyframe_then_its_codes_survive_a_restart(tmp_path):
    basis, geometry, codes, graphs, _ = live_stream(4, realtime=True)
    cfg = settings(tmp_path / "restart")
    first = MapState(cfg)
    feed(first, [basis] + [m for pair in zip(geometry, graphs) for m in pair])
    before = first.map.fused()
    first.close()
    second = MapState(cfg)  # reloads the keyframes without codes, fused for geometry
    assert second.map.without_codes == [g.seq for g in geometry] and second.realtime == {g.seq for g in geometry}
    np.testing.assert_array_equal(second.map.fused().keys, before.keys)
    assert np.all(second.map.fused().code_weight == 0)
    feed(second, codes)
    second.close()
    third = MapState(cfg)  # reloads them with the codes committed after them
    assert third.map.without_codes == []
    assert_same_map(third, whole_map(tmp_path / "whole", 4))
    third.close()


WORKER = textwrap.dedent(
    """
    import sys
    from pathlib import Path
    from tests.test_mapstore_live import live_stream
    from tests.test_mapstore_service import settings
    from services.mapstore.service import handle
    from services.mapstore.state import MapState
    basis, geometry, codes, graphs, _ = live_stream()
    msgs = [basis] + [m for pair in zip(geometry, graphs) for m in pair] + codes
    state = MapState(settings(Path(sys.argv[1])))
    for i, msg in enumerate(msgs[int(sys.argv[2]):], int(sys.argv[2])):
        handle(state, msg, state.cfg)
        print(f"ack {i}", flush=True)
    """
)


@pytest.mark.slow
def test_kill9_after_codes_were_acknowledged_then_restart(tmp_path):
    """A codes-less keyframe, then its codes: each acknowledged only once committed; SIGKILL after half the codes,
    a restart keeps them, and the rest of the stream gives the map of keyframes that carried their codes."""
    basis, geometry, codes, graphs, _ = live_stream()
    msgs = [basis] + [m for pair in zip(geometry, graphs) for m in pair] + codes
    kill_after = len(msgs) - len(codes) // 2 - 1

    def run(start: int, kill_at: int | None) -> int:
        proc = subprocess.Popen([sys.executable, "-c", WORKER, str(tmp_path / "crash"), str(start)],
                                stdout=subprocess.PIPE, text=True, cwd=REPO, env=dict(os.environ, PYTHONPATH=str(REPO)))
        last = start - 1
        for line in proc.stdout:
            last = int(line.split()[1])
            if kill_at is not None and last >= kill_at:
                os.kill(proc.pid, signal.SIGKILL)
                break
        proc.wait()
        return last

    last = run(0, kill_after)
    assert last >= kill_after
    state = MapState(settings(tmp_path / "crash"))
    acked = {m.seq for m in msgs[: last + 1] if isinstance(m, KeyframeCodes)}
    assert acked and acked <= {k for k, c in state.map.contents.items() if c.has_codes}
    assert set(state.map.contents) == {g.seq for g in geometry}
    state.close()
    assert run(last + 1, None) == len(msgs) - 1
    final = MapState(settings(tmp_path / "crash"))
    assert_same_map(final, whole_map(tmp_path / "whole"))
    final.close()


def test_over_zenoh_codes_on_their_key_and_progress_reports(tmp_path, unix_endpoint):
    """(d) the service loop: a keyframe without codes, its codes on ``kmvipe/<s>/codes``, and progress reports on
    ``kmvipe/<s>/progress`` (the highest committed keyframe seq, after each keyframe and as a heartbeat)."""
    basis, geometry, codes, graphs, _ = live_stream(3)
    state = MapState(settings(tmp_path / "zenoh"))
    stop = threading.Event()
    with Bus(BusSettings(listen=[unix_endpoint]), "mapstore") as mbus, \
            Bus(BusSettings(connect=[unix_endpoint]), "tester") as bus:
        reports = bus.inbox({keys.topic(STREAM, keys.PROGRESS): [Credit]})
        worker = threading.Thread(target=mapstore.run, args=(state.cfg, mbus, stop, state), daemon=True)
        worker.start()
        wait_until(lambda: "mapstore" in bus.alive(timeout=0.2), 10, "the mapstore to be alive")

        def next_report(seq: int) -> Credit:
            while (got := reports.get(ACK_S)) is not None:
                assert got.msg.consumer.startswith(f"mapstore-{mbus.instance}.")  # a new name per start
                assert got.msg.checkpoints and got.msg.durable == got.msg.seq  # committed is durable
                if got.msg.seq == seq:
                    return got.msg
                assert got.msg.seq < seq  # reports only move forward
            pytest.fail(f"no progress report of keyframe {seq}")

        assert next_report(-1).stream == STREAM  # the heartbeat, before any keyframe
        bus.publish(keys.topic(STREAM, keys.PCA), basis)
        wait_until(lambda: basis.version in state.bases, ACK_S, "the basis")
        for g, graph in zip(geometry, graphs):
            bus.publish(keys.topic(STREAM, keys.KEYFRAME), g)
            next_report(g.seq)
            bus.publish(keys.topic(STREAM, keys.GRAPH), graph)
        wait_until(lambda: int(graphs[-1].seq) in dict(state.map.poses), ACK_S, "the graphs")

        def stats() -> MapStats:
            return decode(bus.request(keys.map_key(STREAM, "stats"), timeout=2.0), MapStats)

        # committed at once, fused within refresh_period_s
        wait_until(lambda: stats().points > 100, state.cfg.refresh_period_s + ACK_S, "the graphs to be fused")
        assert stats().keyframes_without_codes == 3
        for c in codes:
            bus.publish(keys.topic(STREAM, keys.CODES), c)
        wait_until(lambda: all(state.has_codes(c.seq) for c in codes), ACK_S, "the codes to be fused")
        while reports.get(0) is not None:  # drain, then listen to the idle mapstore: heartbeats
            pass
        heard = [reports.get(1.0) for _ in range(3)]
        assert all(d is not None and d.msg.seq == geometry[-1].seq for d in heard)  # the last committed keyframe
        stats = decode(bus.request(keys.map_key(STREAM, "stats"), timeout=2.0), MapStats)
        assert stats.keyframes_without_codes == 0
        stop.set()
        worker.join(10)
    with state.lock:
        assert_same_map(state, whole_map(tmp_path / "whole", 3))
    state.close()
