"""The mapstore's folding policy (services/mapstore/folding_policy.py) through its service state: over a long stream
keyframes that have left ba's graph fold, and the map is the one without folding; a restart reloads it; a new basis
converts the frozen sums; codes still to come, real-time streams and max_live_keyframes decide when a keyframe may
fold; a folded keyframe's graph updates and repeats stay out. The scene and ba's imitation are
tests/test_mapstore_memory.py's.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from services.common.schema import Eos, Graph, Keyframe, KeyframeCodes, Message
from services.mapstore import queries, state as state_module
from services.mapstore.config import MapstoreSettings
from services.mapstore.core.map import KeyframeMap
from services.mapstore.colmap import read_colmap
from services.mapstore.export import read_ply
from services.mapstore.service import handle, stream_complete
from services.mapstore.state import MapState
from tests.helpers.carving_scene import H, INTR, W, cam_pose, label_codes
from tests.test_mapstore_memory import (COMPONENTS, KEEP, STREAM, Ba, assert_same_fused, basis, keyframe_data,
                                        revised)


def messages(n: int, codes_lag: int | None = None, realtime: bool = False, final: bool = True,
             depth_noise: float = 0.0) -> list[Message]:
    """basis 1, then per keyframe: the keyframe, ba's graph of its window; with ``codes_lag`` the keyframes come
    without codes and each one's codes follow ``codes_lag`` keyframes later (after it left ba's graph when the lag
    exceeds KEEP); the final graph and ba's EOS at the end. ``depth_noise``: relative noise on each disparity."""
    out: list[Message] = [basis(1)]
    ba, truth, image = Ba(), {}, np.full((8 * H, 8 * W, 3), 120, np.uint8)
    pending: list[KeyframeCodes] = []
    for i in range(n):
        pose, disparity, codes = keyframe_data(i, n)
        disparity = disparity * (1 + depth_noise * np.random.default_rng(i).normal(size=disparity.shape))
        truth[i] = pose
        kf = Keyframe(STREAM, i, i * 10**6, image=image, intrinsics=INTR, pca_version=1, codes=codes,
                      realtime=realtime)
        if codes_lag is not None:
            pending.append(KeyframeCodes(STREAM, i, kf.t_ns, pca_version=1, codes=codes))
            kf = dataclasses.replace(kf, codes=None, pca_version=-1)
        out.append(kf)
        window = ba.add(i)
        out.append(Graph(STREAM, i, kf.t_ns, kf_seqs=np.array(window), intrinsics=INTR, width=8 * W, height=8 * H,
                         poses=np.stack([revised(truth[k], k, i) for k in window]), updated_seqs=np.array([i]),
                         disparities=disparity[None], final=final and i == n - 1))
        if codes_lag is not None and len(pending) > codes_lag:
            out.append(pending.pop(0))
    out += pending
    out.append(Eos(STREAM, n - 1, 0, stage="ba", count=n))
    return out


def settings(path: Path, **kw) -> MapstoreSettings:
    """A carving window of 8 keyframes (16 by default) keeps the service tests quick; the core test uses 16. Folded
    voxels do not snap to the folded surface unless asked (``fold_snap_voxels``): without it the folded map is the
    map without folding, which these tests compare with."""
    kw.setdefault("fold_snap_voxels", 0.0)
    return MapstoreSettings(stream=STREAM, db_path=str(path / "{stream}.db"), device="cpu", synchronous="NORMAL",
                            voxel_mode="absolute", voxel_size=0.1, carve_keyframes=8, **kw)


def feed(state: MapState, msgs: list[Message], batch: int = 4) -> list:
    """Handle the messages, re-fused (and folded) ``batch`` at a time as the service's loop does."""
    out = []
    for start in range(0, len(msgs), batch):
        with state.batch():
            for msg in msgs[start : start + batch]:
                out += handle(state, msg, state.cfg)
    return out


def scores(state: MapState) -> np.ndarray:
    """Scores of every voxel for a query vector per label (NaN: no code)."""
    b = basis(1)
    vectors = (np.asarray(b.mean) + label_codes(np.arange(4), noise=0.0).astype(np.float64) @ COMPONENTS)
    return state.index().score(vectors.astype(np.float32))


def test_a_long_stream_holds_a_bounded_window_and_gives_the_map_without_folding(tmp_path):
    n = 300
    msgs = messages(n)
    state = MapState(settings(tmp_path / "fold", export_dir=str(tmp_path / "export")))
    bound = KEEP + state.map.fold_window + 4
    most_live = 0
    for start in range(0, len(msgs) - 1, 4):
        feed(state, msgs[start : min(start + 4, len(msgs) - 1)])
        most_live = max(most_live, len(state.map.live), len(state.map.contents))
    assert most_live <= bound
    assert state.map.folded_count >= n - bound and state.keyframe_count() == n
    assert len(state.map.depths) <= bound + 2 and len(state.intrinsics) <= bound
    # folded keyframes are final: their depth maps and images are in the export folder already
    folded_files = sorted(p.name for p in (tmp_path / "export" / "depth").iterdir())
    assert folded_files == [f"{k:06d}.npz" for k in range(state.map.folded_count)]
    assert len(list((tmp_path / "export" / "images").iterdir())) == state.map.folded_count
    whole = MapState(settings(tmp_path / "whole", fold_keyframes=False, export_dir=str(tmp_path / "whole_export")))
    feed(whole, msgs[:-1])
    assert len(whole.map.contents) == n and whole.map.folded_count == 0
    assert_same_fused(state.map.fused(), whole.map.fused())
    np.testing.assert_allclose(scores(state), scores(whole), atol=1e-5)
    # the end of stream: complete (ba's final graph names only keyframes it holds), the export has every keyframe
    assert stream_complete(state)
    (eos,) = [m for _, m in feed(state, msgs[-1:])]
    assert eos.stage == "mapstore" and eos.count == n
    assert len(read_colmap(tmp_path / "export" / "colmap")) == n
    assert len(list((tmp_path / "export" / "depth").iterdir())) == n
    assert len(read_ply(tmp_path / "export" / "map.ply")) == len(whole.map.fused().keys)
    # ... and it is the export of the map that never folded, written all at the end
    feed(whole, msgs[-1:])
    for kind in ("depth", "images", "colmap"):
        names = sorted(p.name for p in (tmp_path / "export" / kind).iterdir())
        assert names == sorted(p.name for p in (tmp_path / "whole_export" / kind).iterdir()), kind
    for name in ("000000.npz", f"{n - 1:06d}.npz"):
        with np.load(tmp_path / "export" / "depth" / name) as a, np.load(tmp_path / "whole_export" / "depth" / name) as b:
            np.testing.assert_array_equal(a["depth"], b["depth"])
    for name in ("images/000000.jpg", "colmap/images.bin", "colmap/points3D.bin"):
        assert (tmp_path / "export" / name).read_bytes() == (tmp_path / "whole_export" / name).read_bytes(), name
    assert queries.stats(state, STREAM).keyframes == n  # the stats verb counts folded keyframes too
    state.close()
    whole.close()


def test_a_restart_after_folding_reloads_the_same_map_a_page_at_a_time(tmp_path, monkeypatch):
    n, cut = 150, 110
    msgs = messages(n, depth_noise=0.015)
    idx = next(j for j, m in enumerate(msgs) if isinstance(m, Graph) and m.seq == cut)
    snap = MapstoreSettings().fold_snap_voxels  # as deployed: folded voxels join the folded surface
    assert snap > 0
    cfg = settings(tmp_path / "fold", fold_snap_voxels=snap)
    first = MapState(cfg)
    feed(first, msgs[: idx + 1])
    assert first.map.folded_count > 40 and first.map.snapped_voxels > 100
    before, folded, count = first.map.fused(), first.map.folded_count, first.keyframe_count()
    first.close()
    monkeypatch.setattr(state_module, "RESTART_PAGE", 16)
    most_live = []
    refresh = KeyframeMap.refresh

    def watched(self):
        most_live.append(len(self.live))
        return refresh(self)

    monkeypatch.setattr(KeyframeMap, "refresh", watched)
    second = MapState(cfg)
    monkeypatch.setattr(KeyframeMap, "refresh", refresh)
    assert max(most_live) <= 16 + KEEP + second.map.fold_window + 4  # never every keyframe at once
    assert second.map.folded_count == folded and second.keyframe_count() == count
    assert_same_fused(second.map.fused(), before)
    # the stream goes on after the restart and ends as one that was never interrupted
    feed(second, msgs[idx + 1 : -1])
    whole = MapState(settings(tmp_path / "whole", fold_snap_voxels=snap))
    feed(whole, msgs[:-1])
    assert_same_fused(second.map.fused(), whole.map.fused())
    assert second.map.folded_count == whole.map.folded_count
    second.close()
    whole.close()


def test_a_new_basis_after_folding_converts_the_frozen_sums(tmp_path):
    n = 120
    msgs = messages(n)[:-1]
    state, whole = MapState(settings(tmp_path / "fold")), MapState(settings(tmp_path / "whole", fold_keyframes=False))
    for s in (state, whole):
        feed(s, msgs)
    assert state.map.folded_count > 40
    for s in (state, whole):
        feed(s, [basis(2)])
        assert s.map.code_version == 2
    assert_same_fused(state.map.fused(), whole.map.fused(), codes_atol=1e-4)
    got, want = scores(state), scores(whole)
    assert np.isfinite(got).sum() > 100
    np.testing.assert_allclose(got, want, atol=1e-4)
    # and a restart converts the frozen part the same way
    state.close()
    again = MapState(settings(tmp_path / "fold"))
    assert again.map.code_version == 2
    np.testing.assert_allclose(scores(again), want, atol=1e-4)
    again.close()
    whole.close()


def test_codes_still_to_come_keep_a_keyframe_live_until_they_are_in(tmp_path):
    n, lag = 120, KEEP + 20  # each keyframe's codes come well after it left ba's graph
    msgs = messages(n, codes_lag=lag)
    state = MapState(settings(tmp_path / "fold"))
    feed(state, msgs[: len(msgs) // 2])
    coded = max(m.seq for m in msgs[: len(msgs) // 2] if isinstance(m, KeyframeCodes))
    assert 0 < state.map.folded_upto <= coded  # not a keyframe whose codes are still to come ...
    assert state.map.folded_without_codes == 0  # ... nor one without them
    feed(state, msgs[len(msgs) // 2 :])
    assert state.map.folded_count > 0 and state.without_codes_count() == 0 and state.map.folded_without_codes == 0
    whole = MapState(settings(tmp_path / "whole", fold_keyframes=False))
    feed(whole, messages(n))
    assert_same_fused(state.map.fused(), whole.map.fused())
    state.close()
    whole.close()


def test_realtime_keyframes_fold_without_codes_and_late_codes_stay_out_of_the_map(tmp_path):
    n = 100
    msgs = [m for m in messages(n, codes_lag=10**6, realtime=True) if not isinstance(m, KeyframeCodes)]
    cfg = settings(tmp_path / "fold")
    state = MapState(cfg)
    feed(state, msgs[:-1])
    assert state.map.folded_count > 30 and state.map.folded_without_codes == state.map.folded_count
    assert state.without_codes_count() == n
    before = state.map.fused()
    late = KeyframeCodes(STREAM, 3, 0, pca_version=1, codes=keyframe_data(3, n)[2])
    feed(state, [late])  # the backbone's codes for a keyframe folded long ago
    assert state.late_codes == 1 and not state.has_codes(3)
    assert state.store.load().contents[3].has_codes  # committed all the same
    assert_same_fused(state.map.fused(), before)
    state.close()
    again = MapState(cfg)  # a restart folds it as it was folded: without its codes
    assert_same_fused(again.map.fused(), before)
    assert again.without_codes_count() == n
    again.close()


def test_beyond_max_live_keyframes_those_that_left_ba_fold_without_their_codes(tmp_path):
    n = 100
    msgs = [m for m in messages(n, codes_lag=10**6) if not isinstance(m, KeyframeCodes)]  # codes never come
    state = MapState(settings(tmp_path / "fold", max_live_keyframes=70))
    feed(state, msgs[:-1])
    assert 0 < state.map.folded_count and len(state.map.live) <= 70
    assert state.map.folded_without_codes == state.map.folded_count
    state.close()


def test_graph_updates_and_repeats_of_a_folded_keyframe_are_left_out(tmp_path):
    n = 100
    msgs = messages(n)[:-1]
    state = MapState(settings(tmp_path / "fold"))
    feed(state, msgs)
    assert state.map.is_folded(2)
    before = state.map.fused()
    old_pose = state.store.load().poses[2]
    stale = Graph(STREAM, n, 0, kf_seqs=np.array([2, n - 1]), poses=np.stack([cam_pose(9.0), state.map.poses[n - 1]]),
                  intrinsics=INTR, width=8 * W, height=8 * H)
    feed(state, [stale, next(m for m in msgs if isinstance(m, Keyframe) and m.seq == 2)])
    np.testing.assert_array_equal(state.store.load().poses[2], old_pose)  # not committed either
    assert state.keyframe_count() == n
    np.testing.assert_array_equal(state.map.fused().keys, before.keys)
    state.close()


def test_a_keyframe_ba_never_mapped_folds_with_its_codes_and_is_not_counted_without(tmp_path):
    """ba turns a keyframe into a frame before any graph names it (something passing, a burst): it never gets a
    pose or depth, so it folds with no contribution. Its codes came, so it is not among the keyframes without
    codes (the 10,000-frame run reported 18 such keyframes without codes while features skipped none), before
    and after a restart."""
    n, never = 100, 5
    msgs = []
    for m in messages(n)[:-1]:
        if isinstance(m, Graph):
            if m.seq == never:
                continue  # its graph: ba turned it into a frame instead
            keep = m.kf_seqs != never
            m = dataclasses.replace(m, kf_seqs=m.kf_seqs[keep], poses=m.poses[keep])
        msgs.append(m)
    cfg = settings(tmp_path / "fold")
    state = MapState(cfg)
    feed(state, msgs)
    assert state.map.is_folded(never) and state.store.folded_mode(never) == 0
    assert state.keyframe_count() == n and state.without_codes_count() == 0
    state.close()
    again = MapState(cfg)
    assert again.keyframe_count() == n and again.without_codes_count() == 0
    again.close()
