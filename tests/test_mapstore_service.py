"""Mapstore service handlers and queries over a synthetic stream; kill -9 mid-stream and restart."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from services.common.errors import DecodeError
from services.common.schema import Eos, Graph, Keyframe, MapQuery, PcaBasis as PcaMessage, decode
from services.mapstore import queries
from services.mapstore.config import MapstoreSettings
from services.mapstore.colmap import ColmapParams, read_colmap
from services.mapstore.export import read_ply
from services.mapstore.service import handle
from services.mapstore.state import MapState

synth = pytest.importorskip("services.synth")
REPO = Path(__file__).resolve().parents[1]
D, K, STREAM = 32, 8, "t0"


def stream_messages(n_keyframes: int = 8) -> list:
    """pca, then per keyframe: keyframe, graph (all poses, the new depth; earlier poses nudged by BA)."""
    world = synth.SynthWorld(synth.SynthConfig(width=128, height=96, n_frames=2 * n_keyframes))
    vecs = synth.label_vectors(len(world.label_names), D, seed=0)
    rng = np.random.default_rng(0)
    mean = np.zeros(D, np.float32)
    comps = np.linalg.qr(rng.normal(size=(D, K)))[0].T.astype(np.float32)
    msgs = [PcaMessage(STREAM, 0, 0, version=1, backbone="oracle", mean=mean, components=comps)]
    seqs, poses = [], []
    for i in range(0, 2 * n_keyframes, 2):
        f = world.render(i)
        grid = slice(3, None, 8)
        feats = synth.oracle_features(f.labels[grid, grid], vecs, 0.1, rng)
        codes = (feats @ comps.T).astype(np.float16)
        msgs.append(Keyframe(STREAM, i, f.t_ns, image=f.rgb, intrinsics=f.intrinsics, pca_version=1, codes=codes))
        seqs.append(i)
        poses.append(f.world_from_cam)
        nudged = np.array(poses)
        nudged[:-1, 0, 3] += 0.001 * len(seqs)  # BA revises earlier poses a little every time
        disp = (1.0 / f.depth[grid, grid])[None].astype(np.float32)
        msgs.append(Graph(STREAM, i, f.t_ns, kf_seqs=np.array(seqs), poses=nudged, intrinsics=f.intrinsics,
                          width=128, height=96, updated_seqs=np.array([i]), disparities=disp,
                          static_weights=np.where(f.dynamic[grid, grid], 0, 1)[None].astype(np.float32),
                          final=i == 2 * (n_keyframes - 1)))  # ba marks its last graph of a stream final
    msgs.append(Eos(STREAM, 2 * n_keyframes - 1, 0, stage="ba"))
    return msgs


def settings(tmp_path: Path, **kw) -> MapstoreSettings:
    return MapstoreSettings(stream=STREAM, db_path=str(tmp_path / "{stream}.db"), device="cpu", **kw)


def ask(state: MapState, name: str, params: dict | None = None, request: MapQuery | None = None):
    payload = request.encode() if request is not None else None
    return decode(queries.answer(state, STREAM, f"kmvipe/{STREAM}/map/{name}", params or {}, payload))


def test_stream_builds_queryable_map_and_exports(tmp_path):
    cfg = settings(tmp_path, export_dir=str(tmp_path / "export"))
    state = MapState(cfg)
    for msg in stream_messages():
        handle(state, msg, cfg)
    stats = ask(state, "stats")
    assert stats.keyframes == 8 and stats.points > 100 and stats.pca_version == 1
    basis = state.basis()
    query = basis.mean + np.random.default_rng(1).normal(size=K).astype(np.float32) @ basis.components
    answer = ask(state, "query", request=MapQuery(STREAM, 1, 0, vectors=query[None].astype(np.float32), top_k=5,
                                                  with_points=True))
    full = answer.all_scores[0]
    np.testing.assert_allclose(answer.point_score, np.sort(full)[::-1][:5], rtol=1e-5)
    assert answer.n_points == stats.points and len(answer.region_score) >= 1
    assert np.all(answer.region_box_min <= answer.region_centroid) and np.all(answer.region_centroid <= answer.region_box_max)
    seg = ask(state, "segment", request=MapQuery(STREAM, 2, 0, vectors=np.stack([query, -query]).astype(np.float32)))
    np.testing.assert_array_equal(seg.label, (full < 0).astype(np.int32))  # argmax over {q, -q} is the sign
    chunks = [ask(state, "export", {"chunk": str(c), "chunk_size": "100"}) for c in range(stats.points // 100 + 1)]
    assert sum(len(c.xyz) for c in chunks) == stats.points == chunks[0].total_points
    with pytest.raises(DecodeError):
        ask(state, "query", request=None)  # no payload
    assert len(read_ply(tmp_path / "export" / "map.ply")) == stats.points
    cams = read_colmap(tmp_path / "export" / "colmap")
    np.testing.assert_allclose(cams["000014.jpg"].world_from_cam, state.map.poses[14])
    assert (tmp_path / "export" / "images" / "000000.jpg").exists()
    with pytest.raises(KeyError):
        ask(state, "nonsense")
    state.close()


def test_the_export_keeps_the_observations_per_image_the_settings_allow(tmp_path):
    cap = 5
    cfg = settings(tmp_path, export_dir=str(tmp_path / "export"), colmap_points_per_image=cap)
    state = MapState(cfg)
    for msg in stream_messages():
        handle(state, msg, cfg)
    state.close()
    lines = [x for x in (tmp_path / "export" / "colmap" / "images.txt").read_text().splitlines() if x[:1] != "#"]
    observations = [len(line.split()) // 3 for line in lines[1::2]]
    assert len(observations) == 8 and max(observations) == cap  # the cap binds, and holds
    assert MapstoreSettings().colmap_points_per_image == ColmapParams().max_points_per_image  # one default


def test_restart_reloads_identical_map(tmp_path):
    cfg = settings(tmp_path)
    state = MapState(cfg)
    for msg in stream_messages(5):
        handle(state, msg, cfg)
    before = state.map.fused()
    state.close()
    again = MapState(cfg)
    after = again.map.fused()
    np.testing.assert_array_equal(after.keys, before.keys)
    np.testing.assert_allclose(after.xyz, before.xyz, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(after.codes, before.codes, atol=1e-5)
    assert again.map.voxel_size == state.map.voxel_size
    again.close()


WORKER = textwrap.dedent(
    """
    import sys
    from tests.test_mapstore_service import stream_messages, settings
    from services.mapstore.service import handle
    from services.mapstore.state import MapState
    from pathlib import Path
    cfg = settings(Path(sys.argv[1]))
    state = MapState(cfg)
    for i, msg in enumerate(stream_messages()):
        if i >= int(sys.argv[2]):
            handle(state, msg, cfg)
            print(f"ack {i}", flush=True)
    """
)


def run_worker(tmp_path: Path, start: int, kill_after: int | None) -> int:
    """Run the worker from message `start`; SIGKILL it after it acknowledged `kill_after`. Returns the last ack."""
    env = dict(os.environ, PYTHONPATH=str(REPO))
    proc = subprocess.Popen([sys.executable, "-c", WORKER, str(tmp_path), str(start)], stdout=subprocess.PIPE,
                            text=True, cwd=REPO, env=env)
    last = start - 1
    for line in proc.stdout:
        last = int(line.split()[1])
        if kill_after is not None and last >= kill_after:
            os.kill(proc.pid, signal.SIGKILL)
            break
    proc.wait()
    return last


@pytest.mark.slow
def test_kill9_mid_stream_then_restart_equals_uninterrupted_run(tmp_path):
    ref_cfg = settings(tmp_path / "ref")
    ref = MapState(ref_cfg)
    for msg in stream_messages():
        handle(ref, msg, ref_cfg)
    last = run_worker(tmp_path / "crash", 0, kill_after=8)
    assert last >= 8
    state = MapState(settings(tmp_path / "crash"))
    acked_kfs = {m.seq for m in stream_messages()[: last + 1] if isinstance(m, Keyframe)}
    assert acked_kfs <= set(state.map.contents)  # every acknowledged keyframe survived
    state.close()
    assert run_worker(tmp_path / "crash", last + 1, kill_after=None) == len(stream_messages()) - 1
    final = MapState(settings(tmp_path / "crash")).map.fused()
    expect = ref.map.fused()
    np.testing.assert_array_equal(final.keys, expect.keys)
    np.testing.assert_allclose(final.xyz, expect.xyz, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(final.codes, expect.codes, atol=1e-4)


def test_graph_that_overtakes_its_keyframe_is_applied_when_the_keyframe_arrives(tmp_path):
    """keyframe (from features) and graph (from ba) travel on different keys from different services."""
    cfg = settings(tmp_path)
    msgs = stream_messages(3)
    pca = [m for m in msgs if isinstance(m, PcaMessage)]
    kfs = [m for m in msgs if isinstance(m, Keyframe)]
    graphs = [m for m in msgs if isinstance(m, Graph)]
    in_order, swapped = MapState(cfg), MapState(settings(tmp_path / "b"))
    for m in pca + kfs + graphs:
        handle(in_order, m, cfg)
    for m in pca + graphs + kfs:  # every graph before any keyframe
        handle(swapped, m, cfg)
    a, b = in_order.map.fused(), swapped.map.fused()
    assert len(a.keys) > 0
    np.testing.assert_array_equal(np.sort(a.keys), np.sort(b.keys))
    in_order.close()
    swapped.close()


def test_a_diverged_pose_leaves_its_camera_out_of_the_export_not_the_export(tmp_path):
    cfg = settings(tmp_path, export_dir=str(tmp_path / "export"))
    state = MapState(cfg)
    msgs = stream_messages(3)
    for msg in msgs[:-1]:
        handle(state, msg, cfg)
    state.map.poses[2] = np.zeros((4, 4))  # what a diverged BA could send: singular, not a rotation
    out = handle(state, msgs[-1], cfg)  # the EOS: export, then forward
    assert [m.stage for _, m in out] == ["mapstore"]
    cams = read_colmap(tmp_path / "export" / "colmap")
    assert "000000.jpg" in cams and "000002.jpg" not in cams
    state.close()


def fused_one_by_one(tmp_path: Path) -> tuple[list, MapState]:
    """Six keyframes' messages, and the map they make re-fused after each one."""
    msgs = [m for m in stream_messages(6) if not isinstance(m, Eos)]
    one = MapState(settings(tmp_path / "one"))
    for msg in msgs:
        handle(one, msg, one.cfg)
    return msgs, one


def assert_same_fused_map(a: MapState, b: MapState) -> None:
    fa, fb = a.map.fused(), b.map.fused()
    np.testing.assert_array_equal(fa.keys, fb.keys)
    np.testing.assert_allclose(fa.xyz, fb.xyz, atol=1e-9)
    np.testing.assert_allclose(fa.codes, fb.codes, atol=1e-5)


def test_a_batch_commits_each_message_and_fuses_once_to_the_same_map(tmp_path):
    msgs, one = fused_one_by_one(tmp_path)
    batched = MapState(settings(tmp_path / "batched"))
    with batched.batch():
        for msg in msgs:
            handle(batched, msg, batched.cfg)
        assert batched.map.fused().keys.size == 0  # nothing re-fused inside the batch ...
        assert len(batched.store.load().contents) == 6  # ... but every keyframe is committed
    assert_same_fused_map(one, batched)
    one.close()
    batched.close()


def test_batches_that_wait_are_fused_later_in_one_refresh_to_the_same_map(tmp_path):
    msgs, one = fused_one_by_one(tmp_path)
    paced = MapState(settings(tmp_path / "paced"))
    for half in (msgs[: len(msgs) // 2], msgs[len(msgs) // 2:]):
        with paced.batch(refresh=False):
            for msg in half:
                handle(paced, msg, paced.cfg)
        assert paced.map.fused().keys.size == 0  # waiting for the refresh ...
    assert len(paced.store.load().contents) == 6  # ... every keyframe committed
    assert paced.refresh() == 6 and paced.refresh() == 0  # once, then nothing is left to do
    assert_same_fused_map(one, paced)
    assert paced.metric == one.metric
    one.close()
    paced.close()


def test_an_export_inside_the_batch_that_ends_the_stream_writes_everything_committed(tmp_path):
    """The service handles ba's EOS inside a batch that waits for its re-fusion (refresh_period_s, and a slow
    re-fusion holds the next one back): the export it starts must still write the map of every message."""
    msgs, one = fused_one_by_one(tmp_path)
    state = MapState(settings(tmp_path / "batched", export_dir=str(tmp_path / "export")))
    with state.batch(refresh=False):
        for msg in stream_messages(6):  # keyframes, graphs (the last one final) and ba's EOS, in one batch
            out = handle(state, msg, state.cfg)
    assert [m.stage for _, m in out] == ["mapstore"]
    assert_same_fused_map(one, state)
    exported = read_ply(tmp_path / "export" / "map.ply")
    assert len(exported) == len(one.map.fused().keys) > 0
    np.testing.assert_allclose(np.stack([exported[c] for c in "xyz"], 1), one.map.fused().xyz, atol=1e-6)
    assert state.refresh() == 0  # nothing is left for the batch's end or after it
    one.close()
    state.close()


def test_a_query_answers_on_what_is_committed_but_not_re_fused_yet(tmp_path):
    from services.common.schema import MapStats

    state = MapState(settings(tmp_path))
    with state.batch(refresh=False):
        for msg in [m for m in stream_messages(4) if not isinstance(m, Eos)]:
            handle(state, msg, state.cfg)
    assert state.map.fused().keys.size == 0
    answered = decode(queries.answer(state, "cam0", "kmvipe/cam0/map/stats", {}, None), MapStats)
    assert answered.keyframes == 4 and answered.points == state.map.fused().keys.size > 0
    assert state.refresh() == 0  # nothing waits any more
    state.close()


def test_the_map_is_exported_on_the_final_graph_before_bas_end_of_stream(tmp_path, unix_endpoint):
    """Over Zenoh: once ba's final graph and every keyframe it names are in, the mapstore exports (ba solves its
    frames again meanwhile); ba's EOS then only closes the stream, and the EOS forwarded counts the export's time."""
    import threading

    from services.common import keys
    from services.common.bus import Bus
    from services.common.config import BusSettings
    from services.mapstore.service import run
    from tests.conftest import wait_until

    out = tmp_path / "export"
    cfg = settings(tmp_path, export_dir=str(out))
    msgs = stream_messages(4)
    stop = threading.Event()
    with Bus(BusSettings(listen=[unix_endpoint]), "mapstore") as mbus, \
            Bus(BusSettings(connect=[unix_endpoint]), "tester") as bus:
        ends = bus.inbox({keys.topic(STREAM, keys.EOS): [Eos]})
        worker = threading.Thread(target=run, args=(cfg, mbus, stop), daemon=True)
        worker.start()
        wait_until(lambda: "mapstore" in bus.alive(timeout=0.2), 10, "the mapstore to be alive")
        for msg in msgs[:-2]:  # everything but the final graph and the EOS
            bus.publish(keys.topic(STREAM, msg.KIND), msg)
        assert ends.get(1.0) is None and not (out / "map.ply").exists()  # no final graph yet: no export
        bus.publish(keys.topic(STREAM, keys.GRAPH), msgs[-2])
        wait_until(lambda: (out / "colmap" / "points3D.bin").exists(), 20, "the export on the final graph")
        exported_at = (out / "map.ply").stat().st_mtime_ns
        assert ends.get(0.5) is None  # the stream is not over until ba says so
        bus.publish(keys.topic(STREAM, keys.EOS), msgs[-1])
        while (got := ends.get(20.0)) is not None and got.msg.stage != "mapstore":  # ours comes back to us too
            pass
        stop.set()
        worker.join(10)
    assert got is not None and got.msg.stage == "mapstore" and got.msg.count == 4 and got.msg.work_s > 0
    assert (out / "map.ply").stat().st_mtime_ns == exported_at  # not written again
    assert len(read_colmap(out / "colmap")) == 4


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="thread niceness is read from Linux /proc")
def test_the_map_is_fused_on_a_thread_behind_tracking_and_mapping(tmp_path, tcp_endpoint):
    """The stream's thread (commits and re-fusion) runs at ``fusion_nice``; the process's other threads (the bus,
    queries) keep their own priority."""
    import threading

    from services.common.bus import Bus
    from services.common.config import BusSettings
    from services.mapstore.service import run
    from tests.conftest import wait_until

    def niceness() -> dict[int, int]:
        out = {}
        for task in Path("/proc/self/task").iterdir():
            try:
                fields = (task / "stat").read_text().rsplit(")", 1)[1].split()
            except FileNotFoundError:  # a thread (another test's, ending) exited since the listing
                continue
            out[int(task.name)] = int(fields[16])  # field 19 of stat: nice (after pid and comm)
        return out

    before = niceness()
    stop = threading.Event()
    with Bus(BusSettings(mode="peer", listen=[tcp_endpoint]), "mapstore") as bus:
        worker = threading.Thread(target=run, args=(settings(tmp_path, fusion_nice=7), bus, stop), daemon=True)
        worker.start()
        wait_until(lambda: worker.native_id in niceness() and niceness()[worker.native_id] == 7, 30,
                   "the stream thread at niceness 7")
        others = {tid: n for tid, n in niceness().items() if tid != worker.native_id}
        stop.set()
        worker.join(timeout=10)
    assert set(others.values()) <= set(before.values()) | {0}  # nobody else was made nicer


@pytest.mark.parametrize("modules", ["services.mapstore.service, services.mapstore.state",
                                     "services.query_api.service, services.query_api.app, services.query_api.textpath"])
def test_the_map_and_the_gateway_load_torch_only_when_a_query_needs_it(modules):
    # torch is ~2 s of CPU and ~150 MB per process: a mapstore that only builds the map (an edge box, most test
    # pipelines) never needs it, and a gateway only for a language model or an example image; scoring a query
    # (services/mapstore/core/index.py), a CLIP prompt or an example imports it then
    probe = f"import sys, {modules}; print('torch' in sys.modules)"
    done = subprocess.run([sys.executable, "-c", probe], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "False"
