"""A BA linearised in edge slices (``BAParams.linearise_edges``): the same steps as all edges at once, a field of
every edge joined from slices (services/ba/core/slice_fields.py), the kernel constants formed a slice at a time,
and the flow targets taken in the solver's layout without a copy."""
import pytest
import torch

from services.ba.core import ba, irls, synthetic
from services.ba.core import robust as robust_core
from services.ba.core.params import BAParams, RobustParams
from services.ba.core.slice_fields import join_slice
from tests.test_ba_solver import EXACT, _smooth_codes, _start


def test_a_field_formed_in_slices_holds_each_slices_part_and_nothing_of_the_last_evaluation():
    """``join_slice`` joins a slice's field into the field of every edge, reusing the last evaluation's: a kernel
    mask that is None (nowhere) in a slice is False there even where the last evaluation's was True; a broadcast
    part stays a view; a part that is the field's own slice (an ARK cache edge kept) is left as it is."""
    edges = [slice(0, 1), slice(1, 2)]

    def joined(parts, whole=None):
        for part, at in zip(parts, edges):
            whole = join_slice(whole, part, at, 2)
        return whole

    first = joined([torch.tensor([[True, False]]), torch.tensor([[False, True]])])
    assert first.tolist() == [[True, False], [False, True]]
    again = joined([None, torch.tensor([[True, True]])], first)
    assert again is first and again.tolist() == [[False, False], [True, True]]
    assert joined([None, torch.tensor([[True, False]])]).tolist() == [[False, False], [True, False]]
    assert joined([None, None]) is None
    one = torch.full((1, 1), 2.0).expand(1, 3)
    view = joined([one, one])
    assert view.shape == (2, 3) and view.stride() == (0, 0) and view.tolist() == [[2.0] * 3] * 2
    values = torch.arange(6.0).view(2, 3)
    kept = joined([values[0:1], torch.tensor([[9.0, 9.0, 9.0]])], values)
    assert kept is values and kept.tolist() == [[0.0, 1.0, 2.0], [9.0, 9.0, 9.0]]


SHARP_ARK = {"use_ark": True, "kappa": 0.0, "tau": 1e-3, "alpha_dynamic": 0.0}  # L2 (cs > 0.75), Cauchy (cs < -0.04)


@pytest.mark.parametrize("embed,robust", [(0.0, {"use_ark": True}), (1.0, {"use_ark": True}),
                                          (0.0, {"use_ark": False}), (0.0, SHARP_ARK)],
                         ids=["flow", "flow+embedding", "fixed kernel", "ARK with exact L2 and Cauchy pixels"])
def test_a_problem_linearised_in_edge_slices_takes_the_same_steps(embed, robust):
    """A global BA's Jacobians, its residuals and its trial energies are formed a few edges at a time
    (``linearise_edges``), and so are the fields IRLS freezes for an iteration (ARK's cosine cache, refreshed in
    place, and its kernel constants): slices of 3 edges and all edges at once give the same iterations (codes and
    the focal on; ARK or the fixed kernel, whose shape is one broadcast value; ARK shapes that hit the kernel's
    exact special cases, whose masks a slice may lack; parametrised, the embedding term)."""
    win = synthetic.make_window(n=6, h=24, w=32, seed=3, surface="room")
    problem = win.problem._replace(codes=_smooth_codes(6, 24, 32, 8, seed=1))
    start = _start(win, seed=2, focal_factor=1.1)
    assert len(problem.ii) > 3 * 3  # several slices
    runs = {}
    for slices in (0, 3):
        params = BAParams(iterations=6, robust=RobustParams(scale=0.5, **robust), lambda_embed=embed,
                          optimise_focal=True, compute_dtype=EXACT, linearise_edges=slices)
        runs[slices] = ba.run_ba(start, problem, params)
    whole, sliced = runs[0], runs[3]
    assert len(whole.costs) > 3 and whole.costs[-1] < 0.5 * whole.costs[0]  # it did converge somewhere
    assert sliced.costs == pytest.approx(whole.costs, rel=1e-9)
    assert torch.allclose(sliced.state.poses, whole.state.poses, atol=1e-9)
    assert torch.allclose(sliced.state.disparity, whole.state.disparity, rtol=1e-8)
    assert float(sliced.state.intrinsics[0]) == pytest.approx(float(whole.state.intrinsics[0]), rel=1e-10)
    assert torch.allclose(sliced.edge_weight, whole.edge_weight, atol=1e-9)
    assert torch.allclose(sliced.alpha, whole.alpha) and sliced.alpha.shape == whole.edge_weight.shape
    assert torch.allclose(sliced.static_weight, whole.static_weight, atol=1e-9)
    if robust is SHARP_ARK:  # both masks were in play
        assert bool((whole.alpha == 2).any()) and bool((whole.alpha == 0).any())


def test_a_sliced_bas_shapes_keep_no_kernel_constants_of_every_edge():
    """A BA in slices keeps ARK's shapes of every edge and forms their kernel constants a slice at a time (four
    float and three bool fields of every edge were ~50 MB of an 840-edge background BA); a fixed shape keeps its
    broadcast constants."""
    alpha = torch.tensor([[2.0, 0.0, -1.0, 1.0], [-float("inf"), 0.5, -2.0, 2.0], [-1.0, -1.0, 1.5, 0.0]])
    lazy = irls.lazy(alpha, torch.zeros_like(alpha))
    assert lazy.kernel is None
    for edges in (slice(0, 1), slice(1, 3)):
        got, want = irls.sliced(lazy, edges).kernel, robust_core.kernel(alpha[edges], alpha.dtype)
        for g, w in zip(got, want):
            assert (g is None and w is None) or torch.equal(g, w)
    fixed = irls.lazy(torch.full((1, 1), -1.0).expand(3, 4), torch.zeros(3, 4))
    assert fixed.kernel is not None and all(t is None or 0 in t.stride() for t in fixed.kernel)
    assert torch.equal(irls.sliced(fixed, slice(1, 3)).kernel.coef, robust_core.kernel(-1.0).coef.float().expand(2, 4))


def test_targets_stacked_channels_first_reach_the_solver_without_a_copy():
    """The frontend stacks a window's flow targets channels first and hands them over as an (E, h, w, 2) view:
    the solver's layout (E, 2, P) is then that memory itself, not a second copy of every edge's targets."""
    win = synthetic.make_window(n=4, h=6, w=8, seed=0)
    e = len(win.problem.ii)
    channels_first = win.problem.targets.permute(0, 3, 1, 2).float().contiguous()
    params = BAParams()
    prep = ba._prepare(win.problem._replace(targets=channels_first.permute(0, 2, 3, 1)), params, 6, 8)
    assert prep.targets.data_ptr() == channels_first.data_ptr()
    assert torch.equal(prep.targets, win.problem.targets.float().reshape(e, 48, 2).transpose(1, 2))
    copied = ba._prepare(win.problem._replace(targets=win.problem.targets.float()), params, 6, 8)
    assert copied.targets.data_ptr() != win.problem.targets.data_ptr() and torch.equal(copied.targets, prep.targets)
