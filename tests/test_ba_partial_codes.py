"""A BA whose keyframes' codes are not all in (a keyframe's codes follow its geometry): edges between keyframes
with codes use ARK and the embedding term, the others the fixed kernel, and a missing keyframe's placeholder codes
are never read. Before, one keyframe without codes turned ARK off for the whole BA: on the 10,000-frame stream
every background BA ran without it, since the newest keyframe's codes were still on their way."""
from __future__ import annotations

import pytest
import torch

from services.ba.core import ba
from services.ba.core.params import BAParams, RobustParams
from tests.test_ba_solver import EXACT, _moving_object_window, _pose_errors, _smooth_codes

ARK = dict(use_ark=True, alpha_dynamic=-2.0, kappa=0.5, tau=0.05, scale=0.5, fixed_alpha=2.0)  # fixed: L2
MISSING = 5  # the newest keyframe of the window


def _without(problem: ba.BAProblem, placeholder: torch.Tensor) -> ba.BAProblem:
    codes = problem.codes.clone()
    codes[MISSING] = placeholder
    coded = torch.ones(len(codes), dtype=torch.bool)
    coded[MISSING] = False
    return problem._replace(codes=codes, coded=coded)


def _touches_missing(problem: ba.BAProblem) -> torch.Tensor:
    return (problem.ii == MISSING) | (problem.jj == MISSING)


@pytest.mark.parametrize("embed", [0.0, 1.0], ids=["flow", "flow+embedding"])
def test_a_keyframe_without_codes_keeps_its_edges_on_the_fixed_kernel_and_its_placeholder_is_never_read(embed):
    win, problem, start, _ = _moving_object_window()
    params = BAParams(iterations=8, robust=RobustParams(**ARK), lambda_embed=embed, compute_dtype=EXACT)
    zeros = ba.run_ba(start, _without(problem, torch.zeros_like(problem.codes[MISSING])), params)
    garbage = ba.run_ba(start, _without(problem, 5 * torch.randn(problem.codes[MISSING].shape,
                                                                generator=torch.Generator().manual_seed(4),
                                                                dtype=problem.codes.dtype)), params)
    assert garbage.costs == pytest.approx(zeros.costs, rel=1e-12)
    assert torch.allclose(garbage.state.poses, zeros.state.poses, atol=1e-12)
    assert torch.allclose(garbage.static_weight, zeros.static_weight, atol=1e-12)
    touching = _touches_missing(problem)
    assert bool((zeros.alpha[touching] == ARK["fixed_alpha"]).all())
    assert bool((zeros.alpha[~touching] != ARK["fixed_alpha"]).any())  # the others' shapes follow their codes


def test_the_keyframes_with_codes_keep_ark_against_a_moving_object():
    """The moving block pulls a fixed-kernel (L2) BA far off (1.0 m, 20 degrees). With one keyframe's codes
    missing, a third of the edges keep L2 and the block still pulls on them, but ARK on the others halves that
    (0.46 m, 9 degrees): turning ARK off for the whole BA (codes None) gave it all away."""
    win, problem, start, _ = _moving_object_window()
    params = BAParams(iterations=30, robust=RobustParams(**ARK))
    partial = ba.run_ba(start, _without(problem, torch.zeros_like(problem.codes[MISSING])), params)
    none = ba.run_ba(start, problem._replace(codes=None), params)
    every = ba.run_ba(start, problem, params)
    err = {name: _pose_errors(res.state.poses, win.truth.poses)
           for name, res in (("partial", partial), ("none", none), ("every", every))}
    assert err["partial"][0] < 0.6 * err["none"][0] and err["partial"][1] < 0.6 * err["none"][1], err
    assert err["every"][0] < 0.05 * err["partial"][0], err  # every keyframe's codes in: the block is ignored


def test_edges_without_codes_take_the_same_steps_in_slices():
    from services.ba.core import synthetic
    from tests.test_ba_solver import _start

    win = synthetic.make_window(n=6, h=24, w=32, seed=3, surface="room")
    problem = _without(win.problem._replace(codes=_smooth_codes(6, 24, 32, 8, seed=1)), 0.0)
    start = _start(win, seed=2, focal_factor=1.1)
    runs = {}
    for slices in (0, 3):
        params = BAParams(iterations=6, robust=RobustParams(**ARK), lambda_embed=1.0, optimise_focal=True,
                          compute_dtype=EXACT, linearise_edges=slices)
        runs[slices] = ba.run_ba(start, problem, params)
    whole, sliced = runs[0], runs[3]
    assert sliced.costs == pytest.approx(whole.costs, rel=1e-9)
    assert torch.allclose(sliced.state.poses, whole.state.poses, atol=1e-9)
    assert torch.allclose(sliced.alpha, whole.alpha)
    assert bool((whole.alpha[_touches_missing(problem)] == ARK["fixed_alpha"]).all())


def test_coded_must_name_every_keyframe():
    win, problem, start, _ = _moving_object_window()
    with pytest.raises(ValueError, match="coded"):
        ba.run_ba(start, problem._replace(coded=torch.ones(3, dtype=torch.bool)), BAParams(iterations=1))


@pytest.mark.parametrize("per_edge", [True, False])
def test_a_keyframe_graph_whose_newest_codes_are_on_their_way(per_edge):
    """The graph's BA over three keyframes of a synthetic turn, the newest without codes: per edge (background
    and end-of-stream BAs) the edges between the two others use ARK and the newest's the fixed kernel; a window
    BA (``codes_per_edge=False``) keeps the fixed kernel everywhere until the newest's codes are in."""
    import numpy as np

    from tests.test_ba_steps import _profile_graph

    seqs = [0, 4, 8]
    graph, world = _profile_graph("rot1", seqs)
    h, w = graph.grid_hw
    for k, seq in enumerate(seqs):
        graph.poses[k] = torch.from_numpy(np.linalg.inv(world.poses[0]) @ world.poses[seq])
        if k < 2:
            graph.codes[k] = _smooth_codes(1, h, w, 8, seed=k)[0].float()
    window = list(range(len(seqs)))
    pairs = graph.pairs(window, radius=2)
    params = BAParams(iterations=2, robust=RobustParams(**ARK))
    result = graph.run(window, pairs, params, codes_per_edge=per_edge)
    assert result is not None
    newest = torch.tensor([2 in pair for pair in pairs])
    assert bool((result.alpha[newest] == ARK["fixed_alpha"]).all())
    assert bool((result.alpha[~newest] != ARK["fixed_alpha"]).any()) == per_edge


def test_the_window_setting_reaches_the_frontend(monkeypatch):
    from services.ba.settings import BaSettings

    assert not BaSettings().frontend_params().window_ark_per_edge
    monkeypatch.setenv("KMVIPE_BA_WINDOW_ARK_PER_EDGE", "true")
    assert BaSettings().frontend_params().window_ark_per_edge
