"""Live mapping's later work, bounded: frames tracking posed are aligned again with mapping's own flow (in spare
time and at the end of stream, within a time bound), and the end-of-stream BA stops where its caller's bound says.
Checked against the synthetic world's exact trajectory."""
from __future__ import annotations

import copy
import dataclasses
import logging

import numpy as np
import pytest
import torch

from services.ba.core import ba, synthetic
from services.ba.core.params import BAParams, RobustParams
from services.ba.frontend.frontend import FrameInput, Frontend, KeyframeInput
from services.ba.frontend.params import FrontendParams
from services.ba.frontend.refinement import time_bound
from services.common.schema import FrameLite, Keyframe
from tests.test_ba_pipeline_synth import ate_of, synth_stream

L2 = RobustParams(use_ark=False, fixed_alpha=2.0)


def _perturbed_window(seed: int = 1):
    win = synthetic.make_window(n=6, h=24, w=32, seed=0)
    gen = torch.Generator().manual_seed(seed)
    poses = synthetic.perturb_poses(win.truth.poses, 0.05, 2.0, gen)
    start = ba.BAState(poses, torch.full_like(win.truth.disparity, float(win.truth.disparity.mean())),
                       win.truth.intrinsics.clone())
    return win, start


def test_a_stopped_solve_ends_where_it_was_told_with_a_lower_energy():
    win, start = _perturbed_window()
    params = BAParams(iterations=8, robust=L2, rel_tol=0.0)
    asked = []
    stopped = ba.run_ba(start, win.problem, params, should_stop=lambda: asked.append(1) or len(asked) >= 2)
    assert len(asked) == 2  # asked after each iteration, and it stopped at the first True
    assert len(stopped.costs) <= 3 and stopped.costs[-1] < stopped.costs[0]
    full = ba.run_ba(start, win.problem, params)
    assert full.costs[-1] < stopped.costs[-1]  # the bound really cut the solve short
    never = ba.run_ba(start, win.problem, params, should_stop=lambda: False)
    assert never.costs == full.costs
    torch.testing.assert_close(never.state.poses, full.state.poses)


def _live_frontend(params: FrontendParams, msgs, offset_m: float):
    """A frontend fed as the ba service feeds it from a live camera: keyframes real-time, every frame anchored
    where 'tracking' put it: the exact relative pose to its keyframe, moved by ``offset_m`` (tracking's error)."""
    fe = Frontend(params)
    last_kf = None
    for msg in msgs[:-1]:
        if isinstance(msg, Keyframe):
            fe.add_keyframe(KeyframeInput(msg.seq, msg.t_ns, msg.image, msg.intrinsics, msg.codes, realtime=True))
            last_kf = msg.seq
        elif isinstance(msg, FrameLite) and fe.initialised:
            rel = torch.eye(4, dtype=torch.float64)
            rel[:3, 3] = torch.tensor([offset_m, -offset_m, offset_m], dtype=torch.float64)
            fe.add_frame(FrameInput(msg.seq, msg.t_ns, msg.image, (last_kf, rel)))
    return fe


def _frame_ate(world, fe: Frontend) -> float:
    final = fe._update(list(range(len(fe.graph))), every_frame=True).poses
    frames = [i for i, s in enumerate(final.frame_seqs) if s not in fe.graph.seqs]
    return ate_of(world, final.frame_seqs[frames], final.poses[frames])[0]


@pytest.fixture(scope="module")
def live():
    """(world, a live frontend at the end of its stream, before finish); tests take copies."""
    world, msgs = synth_stream(n_frames=60, rendered=24, every=4, width=256)
    # the focal is exact here: no calibration restarts, and a short end-of-stream BA (what is tested is elsewhere)
    params = FrontendParams(focal_after=1000, global_ba=BAParams(iterations=3))
    return world, _live_frontend(params, msgs, offset_m=0.05)


def _copy(fe: Frontend, **params) -> Frontend:
    fe = copy.deepcopy(fe)
    fe.params = dataclasses.replace(fe.params, **params)
    return fe


def test_spare_time_aligns_tracked_frames_again_and_sends_their_revised_poses(live):
    world, fe = live
    fe = _copy(fe)
    assert fe.initialised
    held = fe.frames.unmeasured()
    inside = [s for s in held if s < fe.graph.seqs[-1]]
    assert inside, "frames between keyframes were tracked"
    before = _frame_ate(world, fe)
    revised = []
    while (update := fe.refine_frame()).poses is not None:
        revised += update.poses.frame_seqs.tolist()
        assert len(revised) <= len(held)
    assert revised == sorted(inside)  # oldest first, only those with keyframes on both sides, each once
    after = _frame_ate(world, fe)
    print(f"tracked frames' ATE {before:.4f} m -> {after:.4f} m after mapping aligned them again")
    assert after < 0.5 * before


def test_end_of_stream_aligns_what_is_left_within_its_time_bound(live):
    world, fe = live
    unbounded = _copy(fe, final_align_s=1e9)
    left = len(unbounded.frames.unmeasured())
    unbounded.finish()
    assert not unbounded.frames.unmeasured()
    no_time = _copy(fe, final_align_s=0.0)
    no_time.finish()
    assert len(no_time.frames.unmeasured()) == left  # a bound of 0 s leaves tracking's poses as they were
    assert _frame_ate(world, unbounded) < 0.5 * _frame_ate(world, no_time)


def test_a_time_bound_stops_before_the_iteration_that_would_overrun_it():
    """Iterations of 0.5 s under a 1.8 s bound: the solve stops after the third (1.5 s), where the fourth would end
    at 2.0 s, not after the fourth that passed it; a first iteration already past the bound ends the solve."""
    now = [0.0]
    bound = time_bound(1.8, clock=lambda: now[0])
    stops = []
    for _ in range(4):
        now[0] += 0.5
        stops.append(bound())
    assert stops == [False, False, True, True]
    slow = time_bound(1.0, clock=lambda: now[0])
    now[0] += 1.2
    assert slow()
    assert time_bound(0.0) is None


def test_end_of_stream_ba_bounded_in_time_still_finishes(live):
    world, fe = live
    fe = _copy(fe, global_ba_s=1e-9, final_align_s=0.0)
    expected = sorted(set(fe.graph.seqs) | set(fe.frames.frames))
    calls = []
    original = fe.graph.run

    def run(window, pairs, params, should_stop=None):
        calls.append(should_stop)
        return original(window, pairs, params, should_stop)

    fe.graph.run = run
    final = fe.finish()
    assert len(calls) == 1 and calls[0] is not None and calls[0]()  # the bound reached the solve, already past
    assert np.isfinite(final.poses.poses).all() and final.poses.frame_seqs.tolist() == expected


def test_spare_time_runs_the_global_ba_once_enough_keyframes_joined_and_briefly_for_a_live_stream():
    """Lossless streams: mapping idles between keyframes (the backbone paces them), so the BA over every held
    keyframe runs then, once ``background_ba_every`` keyframes have joined since the last, and the end of stream
    starts from its result. It revises every keyframe (poses and maps go out), keeps the trajectory on the
    truth, and is not due again until more keyframes join. A live stream's mapping runs it too, bounded to
    ``live_background_ba_s`` (or never, at 0), and its end of stream still gives every keyframe its iterations."""
    from services.ba.frontend.params import GraphParams

    world, msgs = synth_stream(n_frames=60, rendered=24, every=3, width=256)
    params = FrontendParams(graph=GraphParams(window=4), live_window=4, background_ba_every=3, focal_after=1000,
                            global_ba=BAParams(iterations=3))
    fe = Frontend(params)
    revised = []
    for msg in msgs[:-1]:
        if isinstance(msg, Keyframe):
            fe.add_keyframe(KeyframeInput(msg.seq, msg.t_ns, msg.image, msg.intrinsics, msg.codes))
            update = fe.refine_globally()
            if update.graph is not None:
                revised.append(update)
                assert fe.refine_globally().graph is None  # not due again until 3 more keyframes join
        else:
            fe.add_frame(FrameInput(msg.seq, msg.t_ns, msg.image))
    # a live stream (at 512x384: its half-size edge flows need the pixels to start the map)
    live_world, live_msgs = synth_stream(n_frames=60, rendered=24, every=3)
    live, never = Frontend(params), Frontend(dataclasses.replace(params, live_background_ba_s=0.0))
    live_bounds, live_revised = [], []
    live._global_ba = lambda bound, keyframes=None, run=live._global_ba: live_bounds.append(bound) or run(bound,
                                                                                                          keyframes)
    for msg in live_msgs[:-1]:
        if isinstance(msg, Keyframe):
            for mapper in (live, never):
                mapper.add_keyframe(KeyframeInput(msg.seq, msg.t_ns, msg.image, msg.intrinsics, msg.codes,
                                                  realtime=True))
            if (live_update := live.refine_globally()).graph is not None:
                live_revised.append(live_update)
            assert never.refine_globally().graph is None
    assert len(live_revised) >= 2 and live_bounds == [params.live_background_ba_s] * len(live_revised)
    assert 0 < params.live_background_ba_s < params.background_ba_s
    rmse, length = ate_of(live_world, live_revised[-1].graph.kf_seqs, live_revised[-1].graph.poses)
    assert rmse < 0.01 * length
    assert len(revised) >= 2
    last = revised[-1].graph
    assert last.updated_seqs.tolist() == last.kf_seqs.tolist() == fe.graph.seqs  # every keyframe revised
    rmse, length = ate_of(world, last.kf_seqs, last.poses)
    assert rmse < 0.01 * length
    # the end of stream only settles what the background BAs refined: its BA is bounded in time then
    bounds = []
    fe._global_ba = lambda bound, keyframes=None, run=fe._global_ba: bounds.append(bound) or run(bound, keyframes)
    fe.finish()
    assert bounds == [params.settled_global_ba_s] and params.settled_global_ba_s > 0
    # unbounded where no background BA ran, or only a live stream's brief ones
    assert params.global_ba_s == 0 and live._end_bound_s() == 0 and live._settle_span() is None


def _streamed_with_background_bas_over(keyframes: int, edges: int = 0):
    """A short synthetic stream through a frontend whose background BAs span ``keyframes`` and ``edges``
    (3-keyframe window)."""
    from services.ba.frontend.params import GraphParams

    world, msgs = synth_stream(n_frames=60, rendered=27, every=3, width=256)
    params = FrontendParams(graph=GraphParams(window=3), background_ba_every=8, background_ba_keyframes=keyframes,
                            background_ba_edges=edges, focal_after=1000, global_ba=BAParams(iterations=3))
    fe = Frontend(params)
    for msg in msgs[:-1]:
        if isinstance(msg, Keyframe):
            fe.add_keyframe(KeyframeInput(msg.seq, msg.t_ns, msg.image, msg.intrinsics, msg.codes))
        else:
            fe.add_frame(FrameInput(msg.seq, msg.t_ns, msg.image))
    return world, fe


def test_a_background_ba_over_the_newest_keyframes_leaves_the_older_ones_where_they_are(caplog):
    """``background_ba_keyframes`` bounds the background BA (its memory and time grow with its edges): it spans the
    newest that many held keyframes, the oldest of them its gauge; the keyframes before them keep their poses and
    maps, and the update carries the maps of the keyframes it spanned only. Its log line says how many steps it
    took (what a time bound leaves of its iterations)."""
    world, fe = _streamed_with_background_bas_over(5)
    g = fe.graph
    assert len(g) >= 7  # more than the 5 it spans and its gauge
    poses, disparity = [p.clone() for p in g.poses], [d.clone() for d in g.disparity]
    with caplog.at_level(logging.INFO, logger="services.ba.frontend.refinement"):
        update = fe.refine_globally()
    logged = [r for r in caplog.records if r.getMessage() == "background BA"]
    assert len(logged) == 1 and logged[0].keyframes == 5 and logged[0].accepted
    assert 1 <= logged[0].steps <= fe.params.global_ba.iterations
    assert update.graph is not None and update.graph.updated_seqs.tolist() == g.seqs[-5:]
    gauge = len(g) - 5
    for k in range(len(g)):
        pose_moved = float((g.poses[k] - poses[k]).abs().max())
        map_moved = float((g.disparity[k] - disparity[k]).abs().max())
        assert (pose_moved == 0) == (k <= gauge), (k, pose_moved)  # the older ones and the gauge keep their pose
        assert (map_moved == 0) == (k < gauge), (k, map_moved)  # the gauge's map is in the BA
    rmse, length = ate_of(world, update.graph.kf_seqs, update.graph.poses)
    assert rmse < 0.01 * length


def test_landmarks_a_background_ba_reaches_take_the_place_of_the_oldest_held_keyframes():
    """The background BA's keyframes are bounded together with the landmarks their loop edges reach (its memory
    is ba's high-water): with a landmark linked, a budget of 5 spans it and the 4 newest held keyframes, a landmark
    no edge reaches stays out, and the held keyframe before them keeps its pose."""
    world, fe = _streamed_with_background_bas_over(5)
    g = fe.graph
    assert len(g) >= 7  # two landmarks, the 4 newest and one held keyframe older than them
    linked, unlinked = g.seqs[0], g.seqs[1]  # the first place, seen again by the newest keyframes (an orbit)
    g.landmarks |= {linked, unlinked}
    g.proximity |= {(g.seqs[-1], linked), (linked, g.seqs[-2])}
    spans = []
    g.run = lambda window, pairs, *args, run=g.run: spans.append([g.seqs[k] for k in window]) or run(window, pairs,
                                                                                                    *args)
    poses = [p.clone() for p in g.poses]
    update = fe.refine_globally()
    newest = [g.seqs[k] for k in g.recent()[-4:]]
    assert spans == [[linked] + newest]
    assert update.graph is not None and update.graph.updated_seqs.tolist() == newest
    for k in range(len(g)):
        moved = float((g.poses[k] - poses[k]).abs().max())
        assert (moved == 0) == (g.seqs[k] not in newest[1:]), (k, moved)  # the gauge and all before it stay


def test_loop_edges_a_background_ba_would_add_take_the_place_of_the_oldest_keyframes_edges():
    """``background_ba_edges`` bounds the background BA's edges too (each costs memory). At 18, those of 5
    keyframes in a row at radius 3, two loop edges between the newest and the fifth newest make 20, so the fifth
    leaves the span (the 4 newest: 12 edges, the loop edges out with it); at 20, and unbounded (0, the default),
    all five stay; the keyframes the span leaves out keep their poses."""
    for edges, spanned in ((18, 4), (20, 5), (0, 5)):
        world, fe = _streamed_with_background_bas_over(5, edges)
        g = fe.graph
        assert len(g) >= 7
        g.proximity |= {(g.seqs[-1], g.seqs[-5]), (g.seqs[-5], g.seqs[-1])}
        runs = []
        g.run = lambda window, pairs, *args, run=g.run: runs.append(([g.seqs[k] for k in window], len(pairs))) or run(
            window, pairs, *args)
        poses = [p.clone() for p in g.poses]
        update = fe.refine_globally()
        assert runs == [(g.seqs[-spanned:], 20 if spanned == 5 else 12)], edges
        assert update.graph is not None and update.graph.updated_seqs.tolist() == g.seqs[-spanned:]
        for k in range(len(g) - spanned + 1):  # the gauge and every keyframe before it stay
            assert float((g.poses[k] - poses[k]).abs().max()) == 0, (edges, k)


def test_end_of_stream_solves_every_measured_frame_again_with_the_flow_it_has():
    """A frame is aligned once its next keyframe comes, against its keyframes and the focal of that moment. A
    calibration that settles late (a 40 deg lens started from the 60 deg prior) leaves early frames' relative poses
    solved on another camera; BAs after it may move its keyframes apart (a keyframe between them turned back into a
    frame: 40 deg lens, 7.3 % of path). Here half the frames are aligned again under an 18 % short focal, the
    other half moved off their anchors as such a BA leaves them. At the end of stream every one is solved again,
    the stale focal first, with the flow it already has."""
    from tests.test_ba_pipeline_synth import feed

    world, msgs = synth_stream(n_frames=60, rendered=24, every=3, width=256)
    fe = Frontend(FrontendParams(global_ba=BAParams(iterations=3)))
    for msg in msgs[:-1]:
        feed(fe, msg)
    measured = sorted(s for s, f in fe.frames.frames.items() if f.targets)
    stale, moved = measured[::2], measured[1::2]
    true_intrinsics = fe.graph.intrinsics.clone()
    fe.graph.intrinsics[0] *= 0.82
    fe.graph.intrinsics[1] *= 0.82
    for seq in stale:
        fe.frames.align(fe.graph, seq)
    fe.graph.intrinsics.copy_(true_intrinsics)
    for seq in moved:  # its relative pose off by a tenth of the way between its keyframes
        frame, (a, b) = fe.frames.frames[seq], fe.frames.bracket(fe.graph, seq)
        frame.anchor_from_cam[:3, 3] += 0.1 * (fe.graph.poses[b][:3, 3] - fe.graph.poses[a][:3, 3]).norm()
    flows = {s: dict(fe.frames.frames[s].targets) for s in measured}
    left = _copy(fe, final_align_s=0.0)  # no time to solve anything again
    fe.finish()
    left.finish()
    focal = float(fe.graph.intrinsics[0])
    assert fe.frames.stale_focal(focal, fe.params.realign_focal_change) == []
    assert left.frames.stale_focal(focal, left.params.realign_focal_change) == stale
    for seq in measured:  # the flow it had, not computed again (a keyframe new beside it brings its own)
        held = fe.frames.frames[seq].targets
        assert all(held[k] is flows[seq][k] for k in flows[seq] if k in held)
    realigned, first = _frame_ate(world, fe), _frame_ate(world, left)
    print(f"frames' ATE {first:.5f} m with half solved under a short focal and half moved, {realigned:.5f} m "
          f"solved again")
    assert realigned < 0.5 * first


@pytest.mark.parametrize("settle_all", [False, True])
def test_after_background_bas_the_end_of_stream_ba_spans_the_keyframes_since_the_last_and_a_window(settle_all):
    """Once background BAs refined the held keyframes during the stream, the end-of-stream BA spans only those that
    joined since the last one and a window before them, the oldest of them its gauge: the keyframes before keep
    their poses and maps (its first iteration over 100 keyframes took 4.5 s, past its 2 s bound). With
    ``settle_all_keyframes`` it spans every held keyframe again. The trajectory stays on the truth either way."""
    from services.ba.frontend.params import GraphParams

    world, msgs = synth_stream(n_frames=60, rendered=36, every=3, width=256)
    params = FrontendParams(graph=GraphParams(window=3), background_ba_every=4, focal_after=1000,
                            global_ba=BAParams(iterations=3), settle_all_keyframes=settle_all,
                            background_ba_s=0.0, settled_global_ba_s=0.0)  # no time bounds: on a loaded machine
    # they cut BAs short, and what moved would depend on its speed
    fe = Frontend(params)
    for msg in msgs[:-1]:
        if isinstance(msg, Keyframe):
            fe.add_keyframe(KeyframeInput(msg.seq, msg.t_ns, msg.image, msg.intrinsics, msg.codes))
            fe.refine_globally()
        else:
            fe.add_frame(FrameInput(msg.seq, msg.t_ns, msg.image))
    g = fe.graph
    gauge = len(g) - fe._since_global - params.graph.window
    assert fe._background_bas >= 2 and gauge >= 2  # keyframes before the span to leave alone
    poses, disparity = [p.clone() for p in g.poses], [d.clone() for d in g.disparity]
    settled = fe.settle_keyframes()
    for k in range(len(g)):
        pose_moved = float((g.poses[k] - poses[k]).abs().max())
        map_moved = float((g.disparity[k] - disparity[k]).abs().max())
        if settle_all:
            assert (pose_moved == 0) == (k == 0), (k, pose_moved)  # every keyframe but the first, the gauge
        else:
            assert (pose_moved == 0) == (k <= gauge), (k, pose_moved)
            assert (map_moved == 0) == (k < gauge), (k, map_moved)
    assert settled.graph.kf_seqs.tolist() == g.seqs  # every keyframe's final pose goes out
    final = fe.solve_frames()
    rmse, length = ate_of(world, final.poses.frame_seqs, final.poses.poses)
    assert rmse < 0.01 * length
