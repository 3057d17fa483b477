"""Dense bundle adjustment (Levenberg-Marquardt) over keyframe poses, grid disparities and the focal length.

Energy (docs of :class:`services.ba.core.params.BAParams` give the weights)::

    E = lambda_photo * sum_{e,p} conf * c^2 * rho_alpha(|target - reproj|, c)       (ARK flow term)
      + lambda_embed * 1/2 sum_{e,p} conf * r_embed^2,   r_embed = 1 - cs  (or sqrt(2 (1 - cs)))
      + alpha_disp * 1/2 sum_{n,p} mask * (d - d_prior)^2

with ``alpha`` per pixel from :func:`services.ba.core.robust.ark_alpha` of the cosine similarity of the
source code and the bilinear sample of the target code map at the reprojection (frozen within an iteration:
IRLS). The flow term is minimised by IRLS: weight ``conf * c^2 * psi(|r|)/|r|`` on both components.

Gauge: the ``fixed_poses`` oldest poses are held fixed. Monocular scale is free without a disparity prior:
the scale direction is kept finite by the damping and, after every accepted step, the window is rescaled about
the oldest camera so that the distance between camera 0 and the first free camera keeps its initial value
(the energy is invariant under this similarity, so this only picks the gauge).

Every pixel of every edge is processed in one batched tensor expression: no Python loop over pixels or edges.
"""
from __future__ import annotations

import logging
from typing import NamedTuple

import torch

from services.ba.core import embedding, projective, robust, schur, se3
from services.ba.core.params import BAParams

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


class BAState(NamedTuple):
    """Variables: poses ``world_from_cam`` (N, 4, 4) float64, disparities (N, h, w), grid intrinsics (4,)."""

    poses: torch.Tensor
    disparity: torch.Tensor
    intrinsics: torch.Tensor  # (fx, fy, cx, cy) of the grid; fx = fy = f is optimised when asked


class BAResult(NamedTuple):
    """Optimised state and diagnostics."""

    state: BAState
    costs: list[float]  # energy before the first and after every accepted iteration
    edge_weight: torch.Tensor  # (E, h, w) robust (ARK) weight in [0, 1] at the final state, 0 where unused
    static_weight: torch.Tensor  # (N, h, w) in [0, 1]: probability each pixel is static (see _static_weight)
    alpha: torch.Tensor  # (E, h, w) robust shape used in the last iteration


class _Residuals(NamedTuple):
    flow: torch.Tensor  # (E, P, 2)
    flow_w: torch.Tensor  # (E, P) confidence * validity
    embed: embedding.EmbeddingResidual | None
    reproj: projective.Reprojection


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


def _residuals(state: BAState, problem: BAProblem, params: BAParams, with_jac: bool) -> _Residuals:
    n, h, w = state.disparity.shape
    pixels = projective.pixel_grid(h, w, state.poses.dtype, state.poses.device)
    disp = state.disparity.reshape(n, -1)[problem.ii]
    rp = projective.reproject(state.poses[problem.ii], state.poses[problem.jj], disp, pixels,
                              state.intrinsics, with_jac)
    flow = problem.targets.reshape(len(problem.ii), -1, 2).to(rp.coords.dtype) - rp.coords
    flow_w = problem.confidence.reshape(len(problem.ii), -1).to(flow.dtype) * rp.valid
    embed = None
    # the cost (no Jacobians) needs codes only for the embedding term: ARK shapes are frozen per iteration
    wanted = params.lambda_embed > 0 or (params.robust.use_ark and with_jac)
    if problem.codes is not None and wanted:
        codes = problem.codes if problem.codes.is_floating_point() else problem.codes.float()
        if codes.dtype == torch.float16:  # half precision arithmetic is slow or missing on CPUs
            codes = codes.float()
        sample = embedding.bilinear_sample(codes, problem.jj, rp.coords,
                                           derivatives=with_jac and params.lambda_embed > 0)
        src = codes.reshape(n, h * w, -1)[problem.ii]
        raw = embedding.embedding_residual(src, sample, params.embed_form)
        d_coords = None if raw.d_coords is None else raw.d_coords.to(flow.dtype)
        embed = embedding.EmbeddingResidual(raw.cosine.to(flow.dtype), raw.residual.to(flow.dtype), d_coords,
                                            raw.valid)
    return _Residuals(flow, flow_w, embed, rp)


class _Frozen(NamedTuple):
    """IRLS quantities frozen within one iteration."""

    alpha: torch.Tensor  # (E, P) robust shape
    embed_weight: torch.Tensor  # (E, P) weight of the embedding residual (0 where unused)


def _frozen(res: _Residuals, params: BAParams) -> _Frozen:
    rob = params.robust
    if rob.use_ark and res.embed is not None:
        alpha = robust.ark_alpha(res.embed.cosine, rob.alpha_static, rob.alpha_dynamic, rob.kappa, rob.tau)
    else:
        alpha = torch.full_like(res.flow_w, rob.fixed_alpha)
    if res.embed is None or params.lambda_embed <= 0:
        return _Frozen(alpha, torch.zeros_like(res.flow_w))
    # The embedding term is trusted only where the pixel looks static: its flow IRLS weight times the ARK
    # probability of "same content" (the sigmoid of cs); otherwise a moving or occluded pixel's codes would
    # pull the geometry just as its flow does.
    static = rob.scale**2 * robust.weight(res.flow.norm(dim=-1), alpha, rob.scale)
    same = torch.sigmoid((res.embed.cosine - rob.kappa) / rob.tau)
    return _Frozen(alpha, params.lambda_embed * res.flow_w * res.embed.valid * static * same)


def _prior_terms(state: BAState, problem: BAProblem, params: BAParams):
    n = state.disparity.shape[0]
    if problem.disp_prior is None or params.alpha_disp <= 0:
        zero = torch.zeros_like(state.disparity.reshape(n, -1))
        return zero, zero, 0.0
    mask = (problem.prior_mask if problem.prior_mask is not None else problem.disp_prior > 0).reshape(n, -1)
    diff = (state.disparity - problem.disp_prior.to(state.disparity.dtype)).reshape(n, -1)
    h = params.alpha_disp * mask.to(diff.dtype)
    return h, -h * diff, float(0.5 * (h * diff**2).sum())


def _cost(state: BAState, problem: BAProblem, params: BAParams, frozen: _Frozen) -> float:
    res = _residuals(state, problem, params, with_jac=False)
    c = params.robust.scale
    total = params.lambda_photo * (res.flow_w * c**2 * robust.rho(res.flow.norm(dim=-1), frozen.alpha, c)).sum()
    if res.embed is not None and params.lambda_embed > 0:
        total = total + 0.5 * (frozen.embed_weight * res.embed.residual**2).sum()
    return float(total) + _prior_terms(state, problem, params)[2]


def _normal_equations(res: _Residuals, params: BAParams, frozen: _Frozen) -> schur.NormalEquations:
    rp, c = res.reproj, params.robust.scale
    irls = c**2 * robust.weight(res.flow.norm(dim=-1), frozen.alpha, c)
    w_flow = (params.lambda_photo * res.flow_w * irls)[..., None].expand(-1, -1, 2)
    # residual = target - coords, so its Jacobian is minus the reprojection Jacobian; only [xi_i, f] columns
    # are formed because d/d xi_j = -d/d xi_i (see schur)
    j_cam = -rp.j_pose_focal  # (E, P, 2, 7)
    j_disp, resid, weight = -rp.j_disp, res.flow, w_flow
    if res.embed is not None and params.lambda_embed > 0:
        g = res.embed.d_coords[..., None, :]  # (E, P, 1, 2), chain rule through the reprojection
        j_cam = torch.cat([j_cam, g @ -j_cam], 2)
        j_disp = torch.cat([j_disp, (g @ -j_disp[..., None])[..., 0]], 2)
        resid = torch.cat([resid, res.embed.residual[..., None]], 2)
        weight = torch.cat([weight, frozen.embed_weight[..., None]], 2)
    return schur.NormalEquations(j_cam, j_disp, resid, weight)


def _apply(state: BAState, step: schur.Step, params: BAParams) -> BAState:
    poses = se3.retract(state.poses, step.poses)
    disp = (state.disparity + step.disparity.view_as(state.disparity)).clamp_min(params.min_disparity)
    intr = state.intrinsics.clone()
    intr[:2] = intr[:2] + step.focal
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


def _free_camera_indices(n_kf: int, params: BAParams, device) -> torch.Tensor:
    free = torch.arange(6 * min(params.fixed_poses, n_kf), 6 * n_kf, device=device)
    if params.optimise_focal:
        free = torch.cat([free, torch.tensor([6 * n_kf], device=device)])
    return free


def run_ba(state: BAState, problem: BAProblem, params: BAParams) -> BAResult:
    """Run ``params.iterations`` LM iterations; see the module docstring for the energy and gauge."""
    _check(state, problem)
    n, h, w = state.disparity.shape
    free = _free_camera_indices(n, params, state.poses.device)
    has_prior = problem.disp_prior is not None and params.alpha_disp > 0
    distance = float((state.poses[1, :3, 3] - state.poses[0, :3, 3]).norm()) if n > 1 else 0.0
    # no anchor when cameras 0 and 1 coincide (e.g. at initialisation): the damping alone holds the scale
    scale_anchor = params.fix_scale and not has_prior and params.fixed_poses == 1 and distance > 1e-9
    lm = params.lm_init
    res = _residuals(state, problem, params, with_jac=True)
    frozen = _frozen(res, params)
    costs = [_cost(state, problem, params, frozen)]
    for it in range(params.iterations):
        prior_h, prior_g, _ = _prior_terms(state, problem, params)
        step = schur.solve(_normal_equations(res, params, frozen), problem.ii, problem.jj, n, free, lm,
                           params.pose_eps, params.disp_eps, prior_h, prior_g)
        trial = _apply(state, step, params)
        if scale_anchor:
            trial = _rescale(trial, 0, 1, distance)
        trial_cost = _cost(trial, problem, params, frozen)
        logger.debug("BA iter %d cost %.6g -> %.6g (lm %.1e)", it, costs[-1], trial_cost, lm)
        if trial_cost < costs[-1]:
            state, lm = trial, lm * params.lm_down
            res = _residuals(state, problem, params, with_jac=True)
            frozen = _frozen(res, params)
            decrease = costs[-1] - trial_cost
            costs.append(_cost(state, problem, params, frozen))
            if decrease <= params.rel_tol * costs[0]:
                break
        else:
            lm *= params.lm_up
            if lm > params.lm_max:
                break
    edge_w = _edge_weight(res, frozen, params)
    static = _static_weight(res, problem, params, n).view(n, h, w)
    return BAResult(state, costs, edge_w.view(-1, h, w), static, frozen.alpha.view(-1, h, w))


def _edge_weight(res: _Residuals, frozen: _Frozen, params: BAParams) -> torch.Tensor:
    """(E, P) robust IRLS weight c^2 psi(r)/r in [0, 1] of the kernel in use; 0 where the edge is unused."""
    c = params.robust.scale
    return c**2 * robust.weight(res.flow.norm(dim=-1), frozen.alpha, c) * (res.flow_w > 0).to(res.flow.dtype)


def _static_weight(res: _Residuals, problem: BAProblem, params: BAParams, n: int) -> torch.Tensor:
    """(N, P) probability that each keyframe pixel is static, from the evidence of all its out-edges.

    With codes (ARK): the ARK sigmoid of the confidence-weighted mean cosine similarity over the edges,
    ``sigmoid((mean cs - kappa) / tau)`` (summing the per-edge log-odds ``(cs - kappa)/tau``: one view where the
    pixel is occluded or lands on a label border does not outvote the others), times the mean flow weight the
    dynamic kernel gives the pixel, ``c^2 psi_{alpha_dyn}(r)/r`` (a rigidly moving object whose codes still
    agree, e.g. the inside of a large moved object, shows up only in its flow). Without codes: the mean
    robust weight of the kernel in use. 1 (no evidence of motion) where no edge sees the pixel.
    """
    rob = params.robust
    votes = res.flow_w
    with_codes = rob.use_ark and res.embed is not None
    if with_codes:
        votes = votes * res.embed.valid
        flow_w = rob.scale**2 * robust.weight(res.flow.norm(dim=-1), rob.alpha_dynamic, rob.scale)
    else:
        flow_w = rob.scale**2 * robust.weight(res.flow.norm(dim=-1), rob.fixed_alpha, rob.scale)
    p = votes.shape[1]
    total = torch.zeros(n, p, dtype=votes.dtype, device=votes.device).index_add_(0, problem.ii, votes)
    seen = total > 0
    denom = total.clamp_min(torch.finfo(votes.dtype).tiny)

    def mean(values: torch.Tensor) -> torch.Tensor:
        return torch.zeros_like(total).index_add_(0, problem.ii, votes * values) / denom

    static = mean(flow_w)
    if with_codes:
        static = static * torch.sigmoid((mean(res.embed.cosine) - rob.kappa) / rob.tau)
    return torch.where(seen, static, torch.ones_like(static))
