"""Damped normal equations of dense BA with the disparities eliminated by a Schur complement.

Camera variables (``n_cam = 6 N + K``): the left tangent of each pose (``6 n .. 6 n + 5``) then the shared
intrinsics (from index ``6 N``): the focal length, and the principal point ``(cx, cy)`` when it is estimated
(``K = 1`` or ``3``; below, ``f`` stands for all of them and ``7`` for ``6 + K``). Disparities: one per keyframe
and grid pixel, ``(N, P)``; their block of the normal matrix is diagonal because each residual touches one
disparity only.

Each residual (edge ``e``, pixel ``p``, component ``r``) depends on ``[pose_i | pose_j | f]`` and one disparity.
With the left-update convention the pose_j Jacobian is exactly minus the pose_i one
(:mod:`services.ba.core.projective`), so only the 7 columns ``[pose_i | f]`` are formed and multiplied; the
13-wide blocks are expanded from 7x7 products at the end (about 3.5x fewer flops than 13 columns).
The camera-disparity coupling is held as its ``[pose_i | f]`` part per source keyframe ``(N, 7, P)`` and its
``pose_j`` part per edge ``(E, 6, P)``; a few keyframes at a time it is packed into compact ``(c, D, P)`` blocks,
``D = 7 + 6 * their largest out-degree`` (:func:`_packed`), so the Schur complement costs ``N * P * D^2``
instead of ``N * P * n_cam^2`` and its memory grows with the edges, not with the busiest keyframe's degree.
"""
from __future__ import annotations

from typing import Iterable, NamedTuple

import torch

# Extra Cholesky jitter (relative to the mean diagonal) tried once if the damped system is not positive definite.
_JITTER = 1e-9


class NormalEquations(NamedTuple):
    """Per-edge Jacobians and weighted residuals, pixels last (``P`` contiguous), ``R`` residual components.

    The per-pixel tensors may be float32: per-pixel products stay in their dtype, every sum over pixels (the
    camera blocks, their gradient and the Schur complement's coupling products) accumulates in the camera
    system's dtype (float64 in BA)."""

    j_cam: torch.Tensor  # (E, 6 + K, R, P) d residual / d [xi_i, f(, cx, cy)]; d / d xi_j = -d / d xi_i
    j_disp: torch.Tensor  # (E, R, P) d residual / d source disparity
    residual: torch.Tensor  # (E, R, P)
    weight: torch.Tensor  # (E, R, P) (0 = unused)


class Step(NamedTuple):
    """Gauss-Newton/LM increment."""

    poses: torch.Tensor  # (N, 6) left tangent per pose (0 for fixed ones)
    focal: torch.Tensor  # () increment of f
    disparity: torch.Tensor  # (N, P)
    principal_point: torch.Tensor  # (2,) increment of (cx, cy); zeros when it is not estimated (K = 1)


def _expansion(dtype, device, n_intr: int = 1) -> torch.Tensor:
    """``(12 + K, 6 + K)`` map from ``[xi_i, f]`` to ``[xi_i, xi_j, f]`` columns (``J_j = -J_i``)."""
    m = torch.zeros(12 + n_intr, 6 + n_intr, dtype=dtype, device=device)
    m[:6, :6] = torch.eye(6, dtype=dtype, device=device)
    m[6:12, :6] = -torch.eye(6, dtype=dtype, device=device)
    m[12:, 6:] = torch.eye(n_intr, dtype=dtype, device=device)
    return m


CHUNK = 32  # edges whose float64 per-pixel copies exist at once
KEYFRAME_CHUNK = 8  # keyframes whose float64 coupling blocks exist at once: each is (7 + 6 * out-degree) x P, 4 MB
# at 10 out-edges on a 48x64 grid (32 at once were a global BA's peak, +105 MB) ...
CHUNK_ROWS = KEYFRAME_CHUNK * (7 + 6 * 6)  # ... fewer where a keyframe has many more out-edges: at most this many
# padded block rows at once (keyframe_chunks)


def chunks(n: int, size: int = CHUNK) -> list[slice]:
    """Consecutive slices of ``size`` covering ``range(n)`` (the last may be shorter)."""
    return [slice(start, min(start + size, n)) for start in range(0, n, size)]


def _edge_slots(ii: torch.Tensor, n_kf: int) -> tuple[torch.Tensor, list[int]]:
    """Rank of each edge among the edges with the same source, and each keyframe's out-degree."""
    counts = torch.bincount(ii, minlength=n_kf)
    order = torch.argsort(ii, stable=True)
    starts = torch.cumsum(counts, 0) - counts
    slot = torch.empty_like(ii)
    slot[order] = torch.arange(len(ii), device=ii.device) - starts[ii[order]]
    return slot, counts.tolist()


def _add_edges(eq: NormalEquations, ii: torch.Tensor, jj: torch.Tensor, n_kf: int, n_ext: int, *,
               expand: torch.Tensor, big_h: torch.Tensor, big_g: torch.Tensor, h_dd: torch.Tensor, g_d: torch.Tensor,
               own: torch.Tensor, target: torch.Tensor) -> None:
    """Sum the normal equations of the edges ``ii -> jj`` into the camera system ``big_h`` (flat) / ``big_g``, the
    disparity diagonal ``h_dd`` / gradient ``g_d`` and the camera-disparity coupling: its ``[xi_i, f]`` part per
    source keyframe (``own``, summed) and its ``xi_j`` part per edge (``target``, these edges' rows), in place."""
    n_edges, n_res, n_pix = eq.j_disp.shape
    n_own = eq.j_cam.shape[1]  # 6 + K
    dtype, dev = big_h.dtype, big_h.device
    wr = eq.weight * eq.residual
    wd = eq.weight * eq.j_disp
    # Sums over thousands of pixels: in float32 their rounding (~1e-7 relative per partial sum) is of the order of
    # what the Schur complement leaves after cancelling when scale or focal are barely observable, so the operands
    # of every reduction are promoted to the camera dtype first (tests/test_schur_conditioning.py)
    h_77 = torch.empty(n_edges, n_own, n_own, dtype=dtype, device=dev)
    g_7 = torch.empty(n_edges, n_own, dtype=dtype, device=dev)
    for chunk in chunks(n_edges):  # the float64 copies of a few edges at a time: a global BA's are GBs at once
        flat_j = eq.j_cam[chunk].reshape(-1, n_own, n_res * n_pix).to(dtype)
        h_77[chunk] = torch.bmm(flat_j * eq.weight[chunk].reshape(len(flat_j), 1, -1).to(dtype), flat_j.transpose(1, 2))
        g_7[chunk] = torch.bmm(flat_j, wr[chunk].reshape(len(flat_j), -1, 1).to(dtype))[..., 0]
    h_cc = expand @ h_77 @ expand.T  # (E, 12 + K, 12 + K) over [xi_i, xi_j, f]
    g_c = -g_7 @ expand.T
    ar6 = torch.arange(6, device=dev)
    cols = torch.cat([6 * ii[:, None] + ar6, 6 * jj[:, None] + ar6,
                      (6 * n_kf + torch.arange(n_own - 6, device=dev)).expand(n_edges, -1)], 1)  # (E, 12 + K)
    big_h.index_add_(0, (cols[:, :, None] * n_ext + cols[:, None, :]).reshape(-1), h_cc.reshape(-1))
    big_g.index_add_(0, cols.reshape(-1), g_c.reshape(-1))
    h_dd.index_add_(0, ii, (wd * eq.j_disp).sum(1).to(h_dd.dtype))
    g_d.index_add_(0, ii, -(wr * eq.j_disp).sum(1).to(g_d.dtype))
    # sum over the few residual components explicitly: a batched matmul of P*E tiny matrices is far slower
    h_cd7 = sum(eq.j_cam[:, :, r] * wd[:, None, r] for r in range(n_res))  # (E, 6 + K, P) = [xi_i, f]
    own.index_add_(0, ii, h_cd7.to(own.dtype))
    target.copy_(-h_cd7[:, :6])


def keyframe_chunks(out_degree: list[int], n_own: int = 7) -> list[slice]:
    """Consecutive keyframe slices whose packed blocks (padded to the slice's largest out-degree; ``n_own`` =
    6 + K rows of their own) hold at most ``CHUNK_ROWS`` rows, ``KEYFRAME_CHUNK`` keyframes at most, one keyframe
    at least."""
    out, start, widest = [], 0, 0
    for k, degree in enumerate(out_degree):
        widest = max(widest, n_own + 6 * degree)
        if k > start and ((k - start + 1) * widest > CHUNK_ROWS or k - start == KEYFRAME_CHUNK):
            out.append(slice(start, k))
            start, widest = k, n_own + 6 * degree
    return out + [slice(start, len(out_degree))] if out_degree else out


def _packed(chunk: slice, own: torch.Tensor, target: torch.Tensor, ii: torch.Tensor, jj: torch.Tensor,
            slot: torch.Tensor, n_kf: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The compact coupling of the keyframes ``chunk``: ``(c, D, P)``, ``D = 6 + K + 6 * their largest
    out-degree`` (``[xi_i, f]`` then one ``xi_j`` slot per out-edge, zero where a keyframe has fewer), and the camera
    column of each row ``(c, D)`` (a padded slot's is the dummy column ``6 N + K``). Packed a chunk at a time from the
    per-keyframe and per-edge parts: padded to the largest out-degree of all keyframes at once, one landmark that
    many revisits reach made every keyframe's block that wide (a background BA's coupling +100 MB)."""
    ar6 = torch.arange(6, device=ii.device)
    n_rows, n_own = chunk.stop - chunk.start, own.shape[1]
    mine = torch.nonzero((ii >= chunk.start) & (ii < chunk.stop)).flatten()
    width = n_own + 6 * (int(slot[mine].max()) + 1 if len(mine) else 0)
    coupling = own.new_zeros(n_rows, width, own.shape[2])
    coupling[:, :n_own] = own[chunk]
    colmap = torch.full((n_rows, width), 6 * n_kf + n_own - 6, dtype=torch.long, device=ii.device)
    colmap[:, :6] = 6 * torch.arange(chunk.start, chunk.stop, device=ii.device)[:, None] + ar6
    colmap[:, 6:n_own] = 6 * n_kf + torch.arange(n_own - 6, device=ii.device)
    if len(mine):
        rows, cols = (ii[mine] - chunk.start)[:, None], n_own + 6 * slot[mine][:, None] + ar6
        coupling[rows, cols] = target[mine]
        colmap[rows, cols] = 6 * jj[mine][:, None] + ar6
    return coupling, colmap


def solve(eq: NormalEquations | Iterable[tuple[slice, NormalEquations]], ii: torch.Tensor, jj: torch.Tensor,
          n_kf: int, free_cam: torch.Tensor, lm: float, pose_eps: float, disp_eps: float, prior_h: torch.Tensor,
          prior_g: torch.Tensor, n_intrinsics: int = 1,
          camera_prior: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None) -> Step:
    """Solve the damped system for the free camera variables and all disparities.

    Args:
        eq: linearised residuals (see :class:`NormalEquations`) of every edge, or of consecutive edge slices one
            at a time as ``(edges, equations)``: each slice's Jacobians are summed into the system and may then
            be freed, so a global BA's need not all exist at once.
        ii, jj: ``(E,)`` source / target keyframe of each edge.
        n_kf: number of keyframes N.
        free_cam: ``(F,)`` long indices of the camera variables that are optimised.
        lm: Levenberg-Marquardt damping, relative to the diagonal.
        pose_eps, disp_eps: absolute diagonal damping of camera / disparity variables.
        prior_h, prior_g: ``(N, P)`` extra disparity diagonal and gradient (disparity prior; zeros if none).
        n_intrinsics: K, the intrinsics the Jacobians carry after the pose (1: the focal; 3: and ``(cx, cy)``).
        camera_prior: ``(indices, diagonal, gradient)`` of a prior on camera variables, added to the system
            before damping (the principal point's pull to its first guess), or None.
    """
    parts = iter([(slice(0, len(ii)), eq)] if isinstance(eq, NormalEquations) else eq)
    item = next(parts, None)  # (edges, equations) of the first slice
    dtype, dev = prior_h.dtype, ii.device  # camera system and step dtype (float64 in BA)
    n_pix = prior_h.shape[1]
    n_own = 6 + n_intrinsics
    n_cam = 6 * n_kf + n_intrinsics
    n_ext = n_cam + 1  # one dummy column for padded slots
    slot, out_degree = _edge_slots(ii, n_kf)
    elimination = keyframe_chunks(out_degree, n_own)  # packed twice per chunk (here
    # and for the back-substitution): kept, every chunk's block at once would be the padded coupling again
    expand = _expansion(dtype, dev, n_intrinsics)  # (12 + K, 6 + K): [xi_i, xi_j, f] from [xi_i, f]
    big_h = torch.zeros(n_ext * n_ext, dtype=dtype, device=dev)
    big_g = torch.zeros(n_ext, dtype=dtype, device=dev)
    pix_dtype = dtype if item is None else item[1].j_disp.dtype  # per-pixel sums stay in the Jacobians' dtype
    h_dd = torch.zeros(n_kf, n_pix, dtype=pix_dtype, device=dev)
    g_d = torch.zeros(n_kf, n_pix, dtype=pix_dtype, device=dev)
    own = torch.zeros(n_kf, n_own, n_pix, dtype=pix_dtype, device=dev)  # coupling of [xi_i, f], per source
    # keyframe
    target = torch.empty(len(ii), 6, n_pix, dtype=pix_dtype, device=dev)  # coupling of xi_j, per edge
    while item is not None:
        edges, part = item
        if part.j_cam.shape[1] != n_own:
            raise ValueError(f"Jacobians of {part.j_cam.shape[1]} camera columns, {n_own} expected "
                             f"(n_intrinsics={n_intrinsics})")
        _add_edges(part, ii[edges], jj[edges], n_kf, n_ext, expand=expand, big_h=big_h, big_g=big_g, h_dd=h_dd,
                   g_d=g_d, own=own, target=target[edges])
        # no reference to a summed slice is left while the next one is formed, so it is formed in the heap this
        # one frees (a for loop's variable would hold it meanwhile)
        item = part = None
        item = next(parts, None)
    h_dd = h_dd + prior_h.to(pix_dtype)
    g_d = g_d + prior_g.to(pix_dtype)
    big_h = big_h.view(n_ext, n_ext)
    if camera_prior is not None:
        index, diagonal, gradient = camera_prior
        big_h[index, index] += diagonal.to(dtype)
        big_g[index] += gradient.to(dtype)

    # Levenberg-Marquardt damping of the full system, then eliminate the disparities a few keyframes at a time
    diag = torch.diagonal(big_h)
    schur = (big_h + torch.diag(lm * diag + pose_eps)).reshape(-1)
    rhs = big_g.clone()
    inv_dd = 1 / (h_dd * (1 + lm) + disp_eps)
    for chunk in elimination:
        coupling, colmap = _packed(chunk, own, target, ii, jj, slot, n_kf)
        coupling64 = coupling.to(dtype)
        scaled = coupling64 * inv_dd[chunk].to(dtype)[:, None, :]
        schur.index_add_(0, (colmap[:, :, None] * n_ext + colmap[:, None, :]).reshape(-1),
                         -torch.bmm(scaled, coupling64.transpose(1, 2)).reshape(-1))
        rhs.index_add_(0, colmap.reshape(-1), -torch.bmm(scaled, g_d[chunk].to(dtype)[:, :, None]).reshape(-1))
        del coupling64, scaled
    schur = schur.view(n_ext, n_ext)
    s_ff = schur[free_cam][:, free_cam]
    chol, info = torch.linalg.cholesky_ex(s_ff)
    if int(info) != 0:
        jitter = _JITTER * torch.diagonal(s_ff).abs().mean() + pose_eps
        chol, info = torch.linalg.cholesky_ex(s_ff + jitter * torch.eye(len(free_cam), dtype=dtype, device=dev))
    if int(info) == 0:
        delta_free = torch.cholesky_solve(rhs[free_cam][:, None], chol)[:, 0]
    else:  # still indefinite (degenerate window): minimum-norm solution
        delta_free = torch.linalg.pinv(s_ff) @ rhs[free_cam]
    delta_cam = torch.zeros(n_ext, dtype=dtype, device=dev)
    delta_cam[free_cam] = delta_free
    delta_d = torch.empty(n_kf, n_pix, dtype=dtype, device=dev)
    for chunk in elimination:
        coupling, colmap = _packed(chunk, own, target, ii, jj, slot, n_kf)
        back = torch.bmm(delta_cam[colmap][:, None], coupling.to(dtype))[:, 0]
        delta_d[chunk] = inv_dd[chunk].to(dtype) * (g_d[chunk].to(dtype) - back)
    principal = delta_cam[6 * n_kf + 1 : 6 * n_kf + 3] if n_intrinsics == 3 else delta_cam.new_zeros(2)
    return Step(delta_cam[: 6 * n_kf].view(n_kf, 6), delta_cam[6 * n_kf], delta_d, principal)
