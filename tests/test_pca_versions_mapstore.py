"""Mapstore with several PCA basis versions: the fused map stays in the latest one, held keyframes, restart.

A synthetic stream (exact poses and depth) is coded with three bases; the map the service builds must equal
one built from every keyframe's codes converted to the latest basis up front (services/common/pca_codes.py).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from services.common.pca_codes import code_map, convert_codes
from services.common.schema import Graph, Keyframe, MapQuery, PcaBasis as PcaMessage, decode
from services.mapstore import queries
from services.mapstore.config import MapstoreSettings
from services.mapstore.core.keyframe import KeyframeContent
from services.mapstore.core.map import KeyframeMap
from services.mapstore.service import handle, stream_complete
from services.mapstore.state import MapState

synth = pytest.importorskip("services.synth")
D, K, STREAM, N_KF = 32, 8, "v0", 8
VERSION_OF_KF = [1, 1, 1, 2, 2, 2, 3, 3]  # the basis features coded each keyframe with (a refit before 3 and 6)


def _bases() -> dict[int, PcaMessage]:
    rng = np.random.default_rng(7)
    out = {}
    for v in (1, 2, 3):
        comps = np.linalg.qr(rng.normal(size=(D, K)))[0].T.astype(np.float32)
        out[v] = PcaMessage(STREAM, 0, 0, version=v, backbone="oracle", mean=(0.1 * rng.normal(size=D)).astype(np.float32),
                            components=comps)
    return out


BASES = _bases()


def stream() -> list[tuple[PcaMessage | None, Keyframe, Graph]]:
    """Per keyframe: the new basis features published before it (or None), the keyframe, ba's graph."""
    world = synth.SynthWorld(synth.SynthConfig(width=128, height=96, n_frames=2 * N_KF))
    vecs = synth.label_vectors(len(world.label_names), D, seed=0)
    rng = np.random.default_rng(0)
    out, seqs, poses, last_version = [], [], [], 0
    for n, i in enumerate(range(0, 2 * N_KF, 2)):
        f = world.render(i)
        grid = slice(3, None, 8)
        basis = BASES[VERSION_OF_KF[n]]
        feats = synth.oracle_features(f.labels[grid, grid], vecs, 0.1, rng)
        codes = ((feats - basis.mean) @ basis.components.T).astype(np.float16)
        kf = Keyframe(STREAM, i, f.t_ns, image=f.rgb, intrinsics=f.intrinsics, pca_version=basis.version, codes=codes)
        seqs.append(i)
        poses.append(f.world_from_cam)
        nudged = np.array(poses)
        nudged[:-1, 0, 3] += 0.001 * len(seqs)  # BA revises earlier poses a little every time
        disp = (1.0 / f.depth[grid, grid])[None].astype(np.float32)
        graph = Graph(STREAM, i, f.t_ns, kf_seqs=np.array(seqs), poses=nudged, intrinsics=f.intrinsics, width=128,
                      height=96, updated_seqs=np.array([i]), disparities=disp, final=n == N_KF - 1,
                      static_weights=np.where(f.dynamic[grid, grid], 0, 1)[None].astype(np.float32))
        out.append((basis if basis.version != last_version else None, kf, graph))
        last_version = basis.version
    return out


def settings(path: Path) -> MapstoreSettings:
    return MapstoreSettings(stream=STREAM, db_path=str(path / "{stream}.db"), device="cpu")


def feed(state: MapState, cfg: MapstoreSettings, steps) -> None:
    for basis, kf, graph in steps:
        for msg in (basis, kf, graph):
            if msg is not None:
                handle(state, msg, cfg)


def converted_reference(state: MapState, kfs: list[Keyframe], target: int) -> KeyframeMap:
    """An unversioned map of the same keyframes, their codes converted to basis ``target`` before fusion, under
    the state's final depths and poses."""
    ref = KeyframeMap(state.cfg.map_params(), voxel_size=state.map.voxel_size)
    for kf in kfs:
        codes = convert_codes(kf.codes, code_map(BASES[kf.pca_version], BASES[target]))
        old = state.map.contents[kf.seq]
        ref.add_content(KeyframeContent(kf.seq, kf.t_ns, codes, old.colours, old.image_hw, target))
        ref.set_depth(kf.seq, state.map.depths[kf.seq])
        ref.set_pose(kf.seq, state.map.poses[kf.seq])
    ref.refresh()
    return ref


def assert_same_map(a: KeyframeMap, b: KeyframeMap) -> None:
    fa, fb = a.fused(), b.fused()
    assert len(fa.keys) > 100
    np.testing.assert_array_equal(fa.keys, fb.keys)
    np.testing.assert_allclose(fa.xyz, fb.xyz, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(fa.weight, fb.weight, rtol=1e-9)
    np.testing.assert_allclose(fa.codes, fb.codes, atol=1e-4)


def test_fused_map_across_refits_equals_codes_converted_up_front(tmp_path):
    cfg, steps = settings(tmp_path), stream()
    state = MapState(cfg)
    feed(state, cfg, steps[:3])
    assert state.map.code_version == 1
    assert_same_map(state.map, converted_reference(state, [kf for _, kf, _ in steps[:3]], 1))
    feed(state, cfg, steps[3:])
    assert state.map.code_version == 3 and state.basis().version == 3 and not state.map.held
    assert_same_map(state.map, converted_reference(state, [kf for _, kf, _ in steps], 3))
    # stored as received: native version and float16 codes
    stored = state.store.load().contents
    assert [stored[kf.seq].pca_version for _, kf, _ in steps] == VERSION_OF_KF
    np.testing.assert_array_equal(stored[steps[0][1].seq].codes, steps[0][1].codes)
    state.close()


def test_queries_are_scored_under_the_latest_basis(tmp_path):
    cfg = settings(tmp_path)
    state = MapState(cfg)
    feed(state, cfg, stream())
    t = np.random.default_rng(3).normal(size=(2, D)).astype(np.float32)
    answer = decode(queries.answer(state, STREAM, f"kmvipe/{STREAM}/map/query", {},
                                   MapQuery(STREAM, 1, 0, vectors=t, top_k=3, with_points=True).encode()))
    b = BASES[3]
    f = b.mean.astype(np.float64) + state.map.fused().codes.astype(np.float64) @ b.components.astype(np.float64)
    cos = (t.astype(np.float64) @ f.T) / np.linalg.norm(t, axis=1)[:, None] / np.linalg.norm(f, axis=1)[None]
    np.testing.assert_allclose(answer.all_scores, cos, atol=1e-4)
    assert decode(queries.answer(state, STREAM, f"kmvipe/{STREAM}/map/stats", {}, None)).pca_version == 3
    state.close()


def test_a_keyframe_before_its_basis_is_held_then_fused(tmp_path):
    cfg, steps = settings(tmp_path), stream()
    state = MapState(cfg)
    feed(state, cfg, steps[:3])
    basis2, kf3, graph3 = steps[3]
    handle(state, kf3, cfg)  # its basis is still on the way (another key)
    handle(state, graph3, cfg)
    assert state.map.held == [kf3.seq] and state.map.code_version == 1
    assert kf3.seq in state.store.load().contents  # durable even while held
    # not fused in basis 1's space: the map is that of the first three keyframes (under graph 3's poses)
    assert_same_map(state.map, converted_reference(state, [kf for _, kf, _ in steps[:3]], 1))
    state.final_keyframes = {kf.seq for _, kf, _ in steps[:4]}
    assert not stream_complete(state)  # an EOS now would wait for the basis
    handle(state, basis2, cfg)
    assert not state.map.held and state.map.code_version == 2 and stream_complete(state)
    assert_same_map(state.map, converted_reference(state, [kf for _, kf, _ in steps[:4]], 2))
    state.close()


def test_an_older_basis_arriving_late_frees_its_keyframes_without_changing_the_version(tmp_path):
    cfg, steps = settings(tmp_path), stream()
    state = MapState(cfg)
    late = steps[0][0]
    feed(state, cfg, [(None, kf, g) for _, kf, g in steps[:3]] + steps[3:5])  # basis 1 not yet received
    assert state.map.held == [kf.seq for _, kf, _ in steps[:3]] and state.map.code_version == 2
    handle(state, late, cfg)
    assert not state.map.held and state.map.code_version == 2
    assert_same_map(state.map, converted_reference(state, [kf for _, kf, _ in steps[:5]], 2))
    state.close()


@pytest.mark.parametrize("stop_after", [4, 8])
def test_restart_from_sqlite_gives_the_uninterrupted_map(tmp_path, stop_after):
    steps = stream()
    whole_cfg = settings(tmp_path / "whole")
    whole = MapState(whole_cfg)
    feed(whole, whole_cfg, steps)
    cfg = settings(tmp_path / "restarted")
    first = MapState(cfg)
    feed(first, cfg, steps[:stop_after])
    first.close()
    second = MapState(cfg)  # reloads keyframes in versions 1..3 and the three bases
    assert second.map.code_version == VERSION_OF_KF[stop_after - 1]
    feed(second, cfg, steps[stop_after:])
    assert second.map.code_version == 3 and not second.map.held
    assert_same_map(second.map, whole.map)
    whole.close()
    second.close()
