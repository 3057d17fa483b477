"""Dense bundle adjustment (Levenberg-Marquardt) over keyframe poses, grid disparities and the intrinsics (the
focal length; with ``BAParams.optimise_principal_point`` the principal point too).

Energy (docs of :class:`services.ba.core.params.BAParams` give the weights)::

    E = lambda_photo * sum_{e,p} conf * c^2 * rho_alpha(|target - reproj|, c)       (ARK flow term)
      + lambda_embed * 1/2 sum_{e,p} conf * r_embed^2,   r_embed = 1 - cs  (or sqrt(2 (1 - cs)))
      + alpha_disp * 1/2 sum_{n,p} mask * (d - d_prior)^2
      + 1/2 |(cx, cy) - principal_point|^2 / principal_point_sigma^2                   (when it is estimated)

with ``alpha`` per pixel from :func:`services.ba.core.robust.ark_alpha` of the cosine similarity of the
source code and the bilinear sample of the target code map at the reprojection (frozen within an iteration:
IRLS). The flow term is minimised by IRLS: weight ``conf * c^2 * psi(|r|)/|r|`` on both components.

Gauge: the ``fixed_poses`` oldest poses are held fixed. Monocular scale is free without a disparity prior:
the scale direction is kept finite by the damping and, after every accepted step, the window is rescaled about
the oldest camera so that the distance between camera 0 and the first free camera keeps its initial value
(the energy is invariant under this similarity, so this only picks the gauge).

Every pixel of every edge is processed in one batched tensor expression: no Python loop over pixels, and over
edges only in slices of ``BAParams.linearise_edges`` (a global BA's Jacobians would not fit in memory at once; its
residuals and trial energies are evaluated slice by slice too, and a fixed kernel's constants are one broadcast
value, so what exists for every edge at once is what IRLS freezes for an iteration — ARK's cosine cache and its
shapes, whose kernel constants are formed a slice at a time — and the residual norms and weights the end's edge
weights need).
"""
from __future__ import annotations

import logging
from typing import Callable, Iterator, NamedTuple

import torch

from services.ba.core import ark as ark_codes
from services.ba.core import embedding, intrinsics, irls, projective, robust, schur, se3
from services.ba.core.params import BAParams
from services.ba.core.slice_fields import join_slice
from services.ba.core.static_weight import static_weight

logger = logging.getLogger(__name__)


class BAProblem(NamedTuple):
    """Observations of one BA window (N keyframes, E directed edges, grid h x w, P = h * w)."""

    ii: torch.Tensor  # (E,) long source keyframe
    jj: torch.Tensor  # (E,) long target keyframe
    targets: torch.Tensor  # (E, h, w, 2) where each source grid pixel lands in the target (grid px)
    confidence: torch.Tensor  # (E, h, w) flow confidence in [0, 1]
    codes: torch.Tensor | None = None  # (N, h, w, K) feature codes (ARK and embedding term); float32 is fastest
    disp_prior: torch.Tensor | None = None  # (N, h, w) prior disparity
    prior_mask: torch.Tensor | None = None  # (N, h, w) 1 where disp_prior is valid
    focal_bounds: tuple[float, float] | None = None  # fx stays inside (grid px): each step is projected onto it,
    # so a focal pushed against a bound still lets poses and depth converge (a result is never thrown away for it)
    principal_point: tuple[float, float] | None = None  # (cx, cy) grid px the principal point's prior pulls to
    # (BAParams.principal_point_sigma); None: where this solve starts
    coded: torch.Tensor | None = None  # (N,) bool: the keyframes whose codes are in ``codes`` (the others' are
    # placeholders): only edges between two of them use ARK and the embedding term, the rest the fixed kernel.
    # None: every keyframe's


class BAState(NamedTuple):
    """Variables: poses ``world_from_cam`` (N, 4, 4) float64, disparities (N, h, w), grid intrinsics (4,)."""

    poses: torch.Tensor
    disparity: torch.Tensor
    intrinsics: torch.Tensor  # (fx, fy, cx, cy) of the grid; fx (and cx, cy) optimised when asked, fy keeps fy/fx


class BAResult(NamedTuple):
    """Optimised state and diagnostics."""

    state: BAState
    costs: list[float]  # energy before the first and after every accepted iteration
    edge_weight: torch.Tensor  # (E, h, w) robust (ARK) weight in [0, 1] at the final state, 0 where unused
    static_weight: torch.Tensor  # (N, h, w) in [0, 1]: probability each pixel is static (core.static_weight)
    alpha: torch.Tensor  # (E, h, w) robust shape used in the last iteration


def _check(state: BAState, problem: BAProblem) -> None:
    n, h, w = state.disparity.shape
    e = problem.ii.shape[0]
    if state.poses.shape != (n, 4, 4) or state.intrinsics.shape != (4,):
        raise ValueError(f"poses (N,4,4) and intrinsics (4,) expected, got {state.poses.shape}, "
                         f"{state.intrinsics.shape}")
    if problem.jj.shape != (e,) or problem.targets.shape != (e, h, w, 2) or problem.confidence.shape != (e, h, w):
        raise ValueError(f"edges (E,), targets (E,{h},{w},2), confidence (E,{h},{w}) expected")
    if problem.codes is not None and problem.codes.shape[:3] != (n, h, w):
        raise ValueError(f"codes must be ({n},{h},{w},K), got {tuple(problem.codes.shape)}")
    if problem.coded is not None and (problem.coded.shape != (n,) or problem.coded.dtype != torch.bool):
        raise ValueError(f"coded must be ({n},) bool, got {tuple(problem.coded.shape)} {problem.coded.dtype}")


class _Prepared(NamedTuple):
    """Observations in the solver's layout (pixels last) and compute dtype, formed once per call."""

    ii: torch.Tensor  # (E,)
    jj: torch.Tensor  # (E,)
    targets: torch.Tensor  # (E, 2, P)
    confidence: torch.Tensor  # (E, P)
    pixels: torch.Tensor  # (P, 2)
    codes: torch.Tensor | None  # (N, h, w, K) float32 or float64
    coded: torch.Tensor | None  # (E,) bool: edges whose two keyframes have codes (None: every edge, or no codes)


def _prepare(problem: BAProblem, params: BAParams, h: int, w: int) -> _Prepared:
    dtype = getattr(torch, params.compute_dtype)
    e, dev = len(problem.ii), problem.targets.device
    # a view, no copy, when the caller's (E, h, w, 2) targets are a channels-first tensor permuted (graph.run)
    targets = problem.targets.reshape(e, h * w, 2).transpose(1, 2).to(dtype).contiguous()
    codes = problem.codes
    if codes is not None and codes.dtype not in (torch.float32, torch.float64):
        codes = codes.float()  # half precision arithmetic is slow or missing on CPUs
    if codes is not None and params.lambda_embed <= 0:  # ARK alone samples them: channels-first storage
        # (ark.sample), copied once here unless the caller's already is (KeyframeGraph.run)
        codes = codes.permute(0, 3, 1, 2).contiguous().permute(0, 2, 3, 1)
    elif codes is not None:  # the embedding term's gathers want channels last: copied once, not per evaluation
        codes = codes.contiguous()
    coded = None
    if codes is not None and problem.coded is not None and not bool(problem.coded.all()):
        coded = problem.coded[problem.ii] & problem.coded[problem.jj]
    return _Prepared(problem.ii, problem.jj, targets, problem.confidence.reshape(e, -1).to(dtype),
                     projective.pixel_grid(h, w, dtype, dev), codes, coded)


def _edges(prep: _Prepared, edges: slice) -> _Prepared:
    return prep._replace(ii=prep.ii[edges], jj=prep.jj[edges], targets=prep.targets[edges],
                         confidence=prep.confidence[edges], coded=None if prep.coded is None else prep.coded[edges])


def _sliced(n_edges: int, params: BAParams) -> bool:
    """Whether a problem of ``n_edges`` forms its Jacobians slice by slice (``BAParams.linearise_edges``)."""
    return 0 < params.linearise_edges < n_edges


class _Residuals(NamedTuple):
    """Residuals of a state (an evaluation in slices keeps only ``flow_norm`` and ``flow_w``: `_evaluate`)."""

    flow: torch.Tensor | None  # (E, 2, P) target - reprojection
    flow_norm: torch.Tensor  # (E, P)
    flow_w: torch.Tensor  # (E, P) confidence * validity
    embed: embedding.EmbeddingResidual | None  # fields (E, P); d_coords (E, P, 2)
    reproj: projective.PlaneReprojection | None


def _edge_slices(n_edges: int, params: BAParams) -> list[slice]:
    """The edge slices a problem is linearised and evaluated in: one of every edge unless ``_sliced``."""
    return schur.chunks(n_edges, params.linearise_edges) if _sliced(n_edges, params) else [slice(0, n_edges)]


def _edge_residuals(state: BAState, prep: _Prepared, params: BAParams, with_jac: bool) -> _Residuals:
    n, h, w = state.disparity.shape
    disp = state.disparity.reshape(n, -1)[prep.ii].to(prep.targets.dtype)
    rp = projective.reproject_planes(state.poses[prep.ii], state.poses[prep.jj], disp, prep.pixels,
                                     state.intrinsics, with_jac,
                                     with_jac and intrinsics.estimates_principal_point(params))
    flow = prep.targets - rp.coords
    flow_w = prep.confidence * rp.valid
    embed = None
    # ARK alone samples codes through its lazy cache (_ark); the embedding term needs them at every evaluation
    if prep.codes is not None and params.lambda_embed > 0:
        sample = embedding.bilinear_sample(prep.codes, prep.jj, rp.coords.transpose(1, 2), derivatives=with_jac)
        raw = embedding.embedding_residual(prep.codes.reshape(n, h * w, -1)[prep.ii], sample, params.embed_form)
        d_coords = None if raw.d_coords is None else raw.d_coords.to(flow.dtype)
        embed = embedding.EmbeddingResidual(raw.cosine.to(flow.dtype), raw.residual.to(flow.dtype), d_coords,
                                            raw.valid)
    # hypot, not vector_norm(dim=1): a reduction over a strided two-element axis is ~40x slower on CPU
    return _Residuals(flow, torch.hypot(flow[:, 0], flow[:, 1]), flow_w, embed, rp)


def _ark(res: _Residuals, prep: _Prepared, params: BAParams,
         cache: ark_codes.ArkCosine | None) -> ark_codes.ArkCosine | None:
    """ARK's code cosine at ``res``'s reprojections (``irls.code_cosine``)."""
    return irls.code_cosine(prep.codes, prep.ii, prep.jj, prep.coded, res.reproj.coords, res.reproj.valid,
                            res.embed, params, cache)


class _Evaluated(NamedTuple):
    """A state's residuals, ARK's code cosine at its reprojections and the IRLS quantities frozen from them."""

    res: _Residuals  # in a problem linearised in slices only flow_norm and flow_w (the end's weights need them)
    ark: ark_codes.ArkCosine | None
    frozen: irls.Frozen
    energy: float  # the flow and embedding energy (the priors' is not in it)


def _evaluate(state: BAState, prep: _Prepared, params: BAParams, with_jac: bool,
              previous: _Evaluated | None) -> _Evaluated:
    """Residuals at ``state``, ARK's cosine (``previous``'s refreshed: see ``_ark``), the frozen IRLS quantities
    and their energy. In a problem linearised in slices (``_sliced``; never with Jacobians there) a slice at a
    time: each slice's fields are written into the fields of every edge, which are ``previous``'s own (``state``
    has replaced its state: nothing reads them again), and of the residuals only ``flow_norm`` and ``flow_w`` are
    kept. Residuals of every edge at once, and every field twice while the next state's were formed beside the
    last, were most of a global BA's peak (docs/BENCHMARKS.md, forty-first session)."""
    cache = None if previous is None else previous.ark
    if with_jac or not _sliced(len(prep.ii), params):
        res = _edge_residuals(state, prep, params, with_jac)
        ark = _ark(res, prep, params, cache)
        frozen = irls.frozen(res.flow_norm, res.flow_w, res.embed, params, ark, prep.coded)
        return _Evaluated(res, ark, frozen, _energy(res, params, frozen))
    n_edges, energy = len(prep.ii), 0.0
    whole = None if previous is None else list(_fields(previous.res, previous.ark, previous.frozen))
    for edges in _edge_slices(n_edges, params):
        part_prep = _edges(prep, edges)
        res = _edge_residuals(state, part_prep, params, False)
        ark = _ark(res, part_prep, params,
                   None if cache is None else ark_codes.ArkCosine(*(t[edges] for t in cache)))
        frozen = irls.frozen(res.flow_norm, res.flow_w, res.embed, params, ark, part_prep.coded)
        energy += _energy(res, params, frozen)
        parts = _fields(res, ark, frozen)
        whole = [join_slice(None if whole is None else w, p, edges, n_edges) for w, p in zip(whole or parts, parts)]
        del res, ark, frozen, parts  # freed before the next slice's are formed
    flow_norm, flow_w, cosine, inside, coords, alpha, embed_weight = whole
    ark = None if cosine is None else ark_codes.ArkCosine(cosine, inside, coords)
    return _Evaluated(_Residuals(None, flow_norm, flow_w, None, None), ark, irls.lazy(alpha, embed_weight), energy)


def _fields(res: _Residuals, ark: ark_codes.ArkCosine | None, frozen: irls.Frozen) -> tuple:
    """The per-edge fields an evaluation in slices keeps, in the order ``_evaluate`` unpacks them (no kernel
    constants: ``irls.lazy``)."""
    return (res.flow_norm, res.flow_w, *((None,) * 3 if ark is None else ark), frozen.alpha, frozen.embed_weight)


def _prior_terms(state: BAState, problem: BAProblem, params: BAParams):
    n = state.disparity.shape[0]
    if problem.disp_prior is None or params.alpha_disp <= 0:
        zero = torch.zeros_like(state.disparity.reshape(n, -1))
        return zero, zero, 0.0
    mask = (problem.prior_mask if problem.prior_mask is not None else problem.disp_prior > 0).reshape(n, -1)
    diff = (state.disparity - problem.disp_prior.to(state.disparity.dtype)).reshape(n, -1)
    h = params.alpha_disp * mask.to(diff.dtype)
    return h, -h * diff, float(0.5 * (h * diff**2).sum())


def _energy(res: _Residuals, params: BAParams, frozen: irls.Frozen) -> float:
    """Flow and embedding energy of evaluated residuals (summed in float64: LM compares close values)."""
    c = params.robust.scale
    flow = res.flow_w * robust.rho(res.flow_norm, frozen.kernel, c)
    total = params.lambda_photo * c**2 * flow.sum(dtype=torch.float64)
    if res.embed is not None and params.lambda_embed > 0:
        total = total + 0.5 * (frozen.embed_weight * res.embed.residual**2).sum(dtype=torch.float64)
    return float(total)


def _cost(state: BAState, prep: _Prepared, problem: BAProblem, params: BAParams, frozen: irls.Frozen,
          guess: torch.Tensor) -> float:
    """The energy at a trial ``state``; in a problem linearised in slices, summed a slice at a time (a trial's
    residuals are only ever summed)."""
    energy = sum(_energy(_edge_residuals(state, _edges(prep, edges), params, False), params,
                         irls.sliced(frozen, edges)) for edges in _edge_slices(len(prep.ii), params))
    return energy + _prior_energy(state, problem, params, guess)


def _prior_energy(state: BAState, problem: BAProblem, params: BAParams, guess: torch.Tensor) -> float:
    """The priors' energy at ``state``: the disparity prior's and the principal point's (pulled to ``guess``)."""
    return _prior_terms(state, problem, params)[2] + intrinsics.principal_energy(state.intrinsics, guess, params)


def _normal_equations(res: _Residuals, params: BAParams, frozen: irls.Frozen) -> schur.NormalEquations:
    """Residuals ``reprojection - target`` (the flow residual's sign flipped, so its Jacobian is the
    reprojection's own and needs no copy) and, with the embedding term, ``r_embed`` as a third component."""
    rp, c = res.reproj, params.robust.scale
    irls_w = c**2 * robust.weight(res.flow_norm, frozen.kernel, c)
    w_flow = (params.lambda_photo * res.flow_w * irls_w)[:, None].expand(-1, 2, -1)
    j_cam, j_disp, resid, weight = rp.jac, rp.j_disp, -res.flow, w_flow
    if res.embed is not None and params.lambda_embed > 0:
        g = res.embed.d_coords.transpose(1, 2)  # (E, 2, P), chain rule through the reprojection
        j_cam = torch.cat([j_cam, (g[:, None] * j_cam).sum(2, keepdim=True)], 2)
        j_disp = torch.cat([j_disp, (g * rp.j_disp).sum(1, keepdim=True)], 1)
        resid = torch.cat([resid, res.embed.residual[:, None]], 1)
        weight = torch.cat([weight, frozen.embed_weight[:, None]], 1)
    return schur.NormalEquations(j_cam, j_disp, resid, weight)


def _linearised(state: BAState, prep: _Prepared, params: BAParams, frozen: irls.Frozen,
                res: _Residuals) -> Iterator[tuple[slice, schur.NormalEquations]]:
    """The normal equations at ``state``: of ``res`` when it holds Jacobians (a problem of one slice), else
    slice by slice, each slice's residuals evaluated again with Jacobians (see ``BAParams.linearise_edges``)."""
    if res.reproj is not None and res.reproj.jac is not None:
        yield slice(0, len(prep.ii)), _normal_equations(res, params, frozen)
        return
    for edges in _edge_slices(len(prep.ii), params):
        part = _edge_residuals(state, _edges(prep, edges), params, with_jac=True)
        equations = _normal_equations(part, params, irls.sliced(frozen, edges))
        del part  # the residuals' other per-pixel fields are not needed by the solve
        yield edges, equations
        del equations  # the caller has summed this slice: freed before the next one is formed


def _apply(state: BAState, step: schur.Step, params: BAParams,
           focal_bounds: tuple[float, float] | None = None) -> BAState:
    """``state`` moved by ``step``: poses retracted (the gauge's kept exactly), disparities clamped above
    ``min_disparity``, the intrinsics inside their bounds (:func:`services.ba.core.intrinsics.apply_step`)."""
    poses = se3.retract(state.poses, step.poses)
    # the gauge's step is zero, but retract's re-orthonormalisation would still move it by round-off, and with
    # it every "fixed" pose a background BA is meant to leave exactly where it was
    fixed = min(params.fixed_poses, len(poses))
    poses[:fixed] = state.poses[:fixed]
    disp = (state.disparity + step.disparity.view_as(state.disparity)).clamp_min(params.min_disparity)
    intr = intrinsics.apply_step(state.intrinsics, step.focal, step.principal_point,
                                 tuple(state.disparity.shape[1:]), params, focal_bounds)
    return BAState(poses, disp, intr)


def _rescale(state: BAState, anchor: int, other: int, distance: float) -> BAState:
    """Similarity about camera ``anchor`` so that |c_other - c_anchor| = distance (energy-invariant)."""
    centres = state.poses[:, :3, 3]
    now = float((centres[other] - centres[anchor]).norm())
    if now < 1e-12:
        return state
    s = distance / now
    poses = state.poses.clone()
    poses[:, :3, 3] = centres[anchor] + s * (centres - centres[anchor])
    return BAState(poses, state.disparity / s, state.intrinsics)


def run_ba(state: BAState, problem: BAProblem, params: BAParams,
           should_stop: Callable[[], bool] | None = None) -> BAResult:
    """Run ``params.iterations`` LM iterations; see the module docstring for the energy and gauge.
    ``should_stop`` is asked after every iteration: True ends the solve there with the state reached (a caller's
    time bound; LM's accepted states only ever lower the energy, so any prefix is a valid result)."""
    _check(state, problem)
    n, h, w = state.disparity.shape
    free = intrinsics.free_camera_indices(n, params, state.poses.device)
    has_prior = problem.disp_prior is not None and params.alpha_disp > 0
    distance = float((state.poses[1, :3, 3] - state.poses[0, :3, 3]).norm()) if n > 1 else 0.0
    # no anchor when cameras 0 and 1 coincide (e.g. at initialisation): the damping alone holds the scale
    scale_anchor = params.fix_scale and not has_prior and params.fixed_poses == 1 and distance > 1e-9
    lm = params.lm_init
    prep = _prepare(problem, params, h, w)
    whole = not _sliced(len(prep.ii), params)  # the Jacobians of every edge at once, kept across rejected steps
    ev = _evaluate(state, prep, params, whole, None)
    guess = (state.intrinsics[2:].clone() if problem.principal_point is None
             else state.intrinsics.new_tensor(problem.principal_point))
    costs = [ev.energy + _prior_energy(state, problem, params, guess)]
    for it in range(params.iterations):
        prior_h, prior_g, _ = _prior_terms(state, problem, params)
        if params.disp_rel_damping > 0:  # damping, not energy: it slows what no flow constrains (BAParams)
            prior_h = prior_h + params.disp_rel_damping / state.disparity.reshape(n, -1).to(prior_h.dtype) ** 2
        principal = intrinsics.principal_prior(state.intrinsics, guess, params, n)
        camera_prior = None if principal is None else principal[:3]  # (indices, diagonal, gradient)
        step = schur.solve(_linearised(state, prep, params, ev.frozen, ev.res), prep.ii, prep.jj, n, free, lm,
                           params.pose_eps, params.disp_eps, prior_h, prior_g, intrinsics.count(params), camera_prior)
        trial = _apply(state, step, params, problem.focal_bounds)
        if scale_anchor:
            trial = _rescale(trial, 0, 1, distance)
        trial_cost = _cost(trial, prep, problem, params, ev.frozen, guess)
        logger.debug("BA iter %d cost %.6g -> %.6g (lm %.1e)", it, costs[-1], trial_cost, lm)
        if trial_cost < costs[-1]:
            state, lm = trial, lm * params.lm_down
            # after the last iteration only the weights are wanted: no Jacobians
            ev = _evaluate(state, prep, params, whole and it + 1 < params.iterations, ev)
            decrease = costs[-1] - trial_cost
            costs.append(ev.energy + _prior_energy(state, problem, params, guess))
            if decrease <= params.rel_tol * costs[0]:
                break
        else:
            lm *= params.lm_up
            if lm > params.lm_max:
                break
        if should_stop is not None and it + 1 < params.iterations and should_stop():
            break
    edge_w = _edge_weight(ev.res, ev.frozen, params)
    static = static_weight(ev.res.flow_norm, ev.res.flow_w, problem.ii, n, params.robust, ev.ark).view(n, h, w)
    return BAResult(state, costs, edge_w.view(-1, h, w), static, ev.frozen.alpha.reshape(-1, h, w).contiguous())


def _edge_weight(res: _Residuals, frozen: irls.Frozen, params: BAParams) -> torch.Tensor:
    """(E, P) robust IRLS weight c^2 psi(r)/r in [0, 1] of the kernel in use; 0 where the edge is unused."""
    c = params.robust.scale
    out = torch.empty_like(res.flow_norm)
    for edges in _edge_slices(len(out), params):  # the kernel constants of a slice at a time (irls.lazy)
        kern = irls.sliced(frozen, edges).kernel
        out[edges] = c**2 * robust.weight(res.flow_norm[edges], kern, c) * (res.flow_w[edges] > 0)
    return out
