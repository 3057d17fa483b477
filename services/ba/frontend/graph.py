"""Keyframe storage, cached flow targets and the windowed / global BA calls (pure: no transport)."""
from __future__ import annotations

import logging
import math
from dataclasses import replace
from typing import Callable, NamedTuple

import cv2
import numpy as np
import torch

from services.ba.core import flow as core_flow
from services.ba.core.ba import BAProblem, BAResult, BAState, run_ba
from services.ba.core.params import GRID, BAParams, FlowParams
from services.ba.core.projective_numpy import induced_flow_field, translational_parallax
from services.ba.frontend.edges import temporal_pairs
from services.common.camera import scale_intrinsics
from services.common.image_texture import texture as image_texture
from services.common.own_pages import own_pages

logger = logging.getLogger(__name__)
STILL_STEP = 0.01  # keyframe steps below this x the scene's median depth are never refused as jumps (_jumped)


def grid_intrinsics(work: np.ndarray) -> torch.Tensor:
    """Working-resolution (fx, fy, cx, cy) -> 1/8-grid intrinsics ``(4,)`` float64 (resize rule, s = 1/8)."""
    return torch.from_numpy(scale_intrinsics(work, 1 / GRID, 1 / GRID))


def working_intrinsics(grid: torch.Tensor) -> np.ndarray:
    """1/8-grid intrinsics ``(4,)`` -> working-resolution (fx, fy, cx, cy) float64."""
    return scale_intrinsics(grid.detach().cpu().numpy(), GRID, GRID)


def own_pages_tensor(tensor: torch.Tensor) -> torch.Tensor:
    """:func:`services.common.own_pages.own_pages` of a CPU tensor, for what the graph keeps across BAs (a tensor
    on another device is returned as it is: its memory is not the process's heap)."""
    if tensor.device.type != "cpu":
        return tensor
    return torch.from_numpy(own_pages(tensor.detach().numpy()))


class NativeCodes(NamedTuple):
    """A keyframe's codes as features sent them, kept so they can be mapped into any later basis version."""

    version: int  # PCA basis version they were coded with
    codes: np.ndarray  # (h, w, K) float16 (or float32)


class Targets(NamedTuple):
    """Flow targets of one directed edge on the grid."""

    target: torch.Tensor  # (h, w, 2) float32 grid coordinates in the target image
    confidence: torch.Tensor  # (h, w) float32 in [0, 1]


class KeyframeGraph:
    """Keyframes (grey image, codes, prior, pose, disparity) in seq order, proximity edges and a flow cache.

    Keyframes are addressed by their position ``k`` in the list; edges are stored by seq so that removing a
    keyframe does not renumber them. Poses are world_from_cam float64 on ``device``.
    """

    def __init__(self, grid_intrinsics: torch.Tensor, grid_hw: tuple[int, int], flow: FlowParams,
                 device: torch.device, focal_range: tuple[float, float] = (0.36, 1.75), max_step_growth: float = 4.0):
        self.intrinsics = grid_intrinsics.to(device, torch.float64)  # (4,) fx, fy, cx, cy of the grid
        self.first_focal = float(grid_intrinsics[0])
        self.first_principal = (float(grid_intrinsics[2]), float(grid_intrinsics[3]))  # where the principal point's
        # prior holds it (BAParams.principal_point_sigma)
        self.focal_range = focal_range  # BA keeps the focal inside this range of the first guess
        self.grid_hw = grid_hw
        self.flow_params = flow
        self.device = device
        self.seqs: list[int] = []
        self.stamps: list[int] = []
        self.images: list[np.ndarray] = []  # (H, W) uint8 grey, working resolution
        self.codes: list[torch.Tensor | None] = []  # (h, w, K) float32, all in the service's current PCA version
        self.native_codes: list[NativeCodes | None] = []  # as received (None: the keyframe came without codes)
        self.priors: list[torch.Tensor | None] = []  # (h, w) float64 disparity prior (0 = none)
        self.poses: list[torch.Tensor] = []  # (4, 4) float64
        self.disparity: list[torch.Tensor] = []  # (h, w) float64
        self.static: list[torch.Tensor] = []  # (h, w) float32 ARK static weight
        self.confidence: list[torch.Tensor] = []  # (h, w) float32 mean out-edge flow confidence
        self.proximity: set[tuple[int, int]] = set()  # directed (seq_i, seq_j)
        # seqs of keyframes held past keep_keyframes as the places a camera comes back to: the oldest keyframe of
        # each place, fixed, so that loop edges to them tie later laps to the first (Frontend._retire)
        self.landmarks: set[int] = set()
        self._cache: dict[tuple[int, int], Targets] = {}
        # Once poses and depths mean something, DIS starts from the flow they induce: from zero it loses the
        # near road and parked cars of a car doing 0.8 m/frame (KITTI 07), and the scale collapses.
        self.predict_flow = False
        self.max_step_growth = max_step_growth  # see _jumped
        self.jumped_seq: int | None = None  # the keyframe whose step made the last BA result implausible
        # Edges whose flow is computed from now on use images at 1/flow_downscale of the working size (a live
        # camera's mapping: 4x less DIS per edge); grid coordinates come out the same, so cached targets of
        # either size mix in one BA
        self.flow_downscale = 1
        self.full_size_below_parallax = 0.0  # ... except, on a lossless stream, pairs with less parallax (working px)
        self.flow_preset: str | None = None  # DIS preset of new edge flows instead of flow_params' (live streams)
        self._small: dict[int, np.ndarray] = {}  # seq -> grey image at 1/flow_downscale
        self._texture: dict[int, float] = {}  # seq -> services.common.image_texture of its working image

    def __len__(self) -> int:
        return len(self.seqs)

    def __setstate__(self, state: dict) -> None:
        state.setdefault("landmarks", set())  # a checkpoint written before landmarks existed
        state.setdefault("full_size_below_parallax", 0.0)  # ... or before this rule
        if "first_principal" not in state:  # ... or before the principal point was refined: it was held at its
            # first guess, so that is where the intrinsics still have it
            state["first_principal"] = tuple(float(v) for v in state["intrinsics"][2:])
        self.__dict__.update(state)

    def index(self, seq: int) -> int:
        return self.seqs.index(seq)

    def append(self, seq: int, stamp: int, grey: np.ndarray, codes, prior, pose: torch.Tensor,
               disparity: torch.Tensor, native_codes: NativeCodes | None = None) -> int:
        h, w = self.grid_hw
        self.seqs.append(seq)
        self.stamps.append(stamp)
        self.images.append(own_pages(grey))
        self.codes.append(None if codes is None else own_pages_tensor(codes))
        self.native_codes.append(None if native_codes is None else native_codes._replace(
            codes=own_pages(native_codes.codes)))
        self.priors.append(None if prior is None else own_pages_tensor(prior))
        self.poses.append(own_pages_tensor(pose))
        self.disparity.append(own_pages_tensor(disparity))
        self.static.append(own_pages_tensor(torch.ones(h, w)))
        self.confidence.append(own_pages_tensor(torch.zeros(h, w)))
        return len(self.seqs) - 1

    def snapshot(self) -> tuple:
        """The estimated state (poses, disparities, weights, intrinsics), for :meth:`restore`."""
        return ([p.clone() for p in self.poses], [d.clone() for d in self.disparity], list(self.static),
                list(self.confidence), self.intrinsics.clone())

    def restore(self, state: tuple) -> None:
        poses, disparity, static, confidence, intrinsics = state
        self.poses, self.disparity = [p.clone() for p in poses], [d.clone() for d in disparity]
        self.static, self.confidence, self.intrinsics = list(static), list(confidence), intrinsics.clone()

    def remove(self, k: int) -> None:
        """Drop keyframe ``k`` with its proximity edges and cached targets."""
        seq = self.seqs[k]
        for store in (self.seqs, self.stamps, self.images, self.codes, self.native_codes, self.priors, self.poses,
                      self.disparity, self.static, self.confidence):
            del store[k]
        self.proximity = {e for e in self.proximity if seq not in e}
        self.landmarks.discard(seq)
        self._cache = {e: t for e, t in self._cache.items() if seq not in e}
        self._small.pop(seq, None)
        self._texture.pop(seq, None)

    def recode(self, convert: Callable[[NativeCodes], torch.Tensor | None]) -> list[int]:
        """Replace every keyframe's BA codes by ``convert`` of the codes it arrived with (a new PCA version: ARK and
        the embedding term compare codes across keyframes, so all must be in one version). Keyframes that came
        without native codes keep theirs. Returns the seqs ``convert`` left without codes."""
        for k, native in enumerate(self.native_codes):
            if native is not None:
                self.codes[k] = convert(native)
        return [s for s, c, n in zip(self.seqs, self.codes, self.native_codes) if c is None and n is not None]

    def targets(self, i: int, j: int) -> Targets:
        """Cached flow targets of keyframe ``i`` into keyframe ``j`` (positions)."""
        key = (self.seqs[i], self.seqs[j])
        if key not in self._cache:
            scale = self._flow_scale(i, j)
            fwd = bwd = None
            if self.predict_flow:
                fwd, bwd = (induced_flow_field(self.poses[a], self.poses[b], self.disparity[a], self.intrinsics,
                                               GRID // scale) for a, b in ((i, j), (j, i)))
            # at 1/scale a grid cell is grid/scale pixels and grid coordinates come out the same; fb_sigma is
            # in the pixels of that size
            params = self.flow_params if scale == 1 else replace(
                self.flow_params, grid=self.flow_params.grid // scale, fb_sigma=self.flow_params.fb_sigma / scale)
            if self.flow_preset is not None:  # a live keyframe's cheap flow
                params = replace(params, preset=self.flow_preset)
            else:
                params = self.for_texture(params, i, j)
            # both directions at once: the reverse edge is (almost) always asked for too (temporal edges come
            # in pairs), and its two flows are these
            there, back = core_flow.pair_targets(self._image(i, scale), self._image(j, scale), params, fwd, bwd)
            self._cache[key] = Targets(torch.from_numpy(own_pages(there.target)),
                                       torch.from_numpy(own_pages(there.confidence)))
            self._cache.setdefault((self.seqs[j], self.seqs[i]),
                                   Targets(torch.from_numpy(own_pages(back.target)),
                                           torch.from_numpy(own_pages(back.confidence))))
        return self._cache[key]

    def take_flows(self, i: int, j: int) -> dict[tuple[int, int], Targets]:
        """Remove and return the cached targets between keyframes ``i`` and ``j`` (both directions): the next
        :meth:`targets` computes them afresh, from the flow the poses then induce. :meth:`put_flows` keeps them."""
        keys = ((self.seqs[i], self.seqs[j]), (self.seqs[j], self.seqs[i]))
        return {key: self._cache.pop(key) for key in keys if key in self._cache}

    def put_flows(self, flows: dict[tuple[int, int], Targets]) -> None:
        self._cache.update(flows)

    def for_texture(self, params: FlowParams, *ks: int) -> FlowParams:
        """``params`` for flows between keyframes ``ks`` (:meth:`FlowParams.for_texture` of the barer one): bare
        walls may get denser DIS patches."""
        return params.for_texture(self._pair_texture(*ks))

    def _pair_texture(self, *ks: int) -> float:
        """The texture of the barer of keyframes ``ks``, measured only when the bare-wall rule is on (off: inf)."""
        if self.flow_params.low_texture_patch_stride is None:
            return math.inf
        return min(self.texture(k) for k in ks)

    def texture(self, k: int) -> float:
        """How much keyframe ``k``'s working image shows (its flows' DIS patch stride, FlowParams.for_texture)."""
        seq = self.seqs[k]
        if seq not in self._texture:
            self._texture[seq] = image_texture(self.images[k])
        return self._texture[seq]

    def _flow_scale(self, i: int, j: int) -> int:
        """1/size of the images keyframes ``i`` and ``j``'s flows are computed at: ``flow_downscale``, except that a
        lossless stream keeps the working size for a pair where half the size loses what carries the estimate:
        a bare pair (:meth:`FlowParams.is_bare`, the pairs that get dense patches), since half the size leaves DIS
        half of what little a bare wall shows (TartanAir hospital: 0.90 % of path at the working size, 1.18 % with
        every flow at half); and a pair whose poses predict under ``full_size_below_parallax`` working px of
        translational parallax, whose depth and translation are in flow differences of a pixel or two
        (docs/BENCHMARKS.md)."""
        scale = self.flow_downscale
        if scale == 1 or self.flow_preset is not None:
            return scale
        if self.flow_params.is_bare(self._pair_texture(i, j)):
            return 1
        if self.full_size_below_parallax > 0:
            parallax = translational_parallax(self.poses[i], self.poses[j], self.disparity[i], self.intrinsics)
            if parallax * self.flow_params.grid < self.full_size_below_parallax:
                return 1
        return scale

    def _image(self, k: int, scale: int) -> np.ndarray:
        """Keyframe ``k``'s grey image at 1/``scale`` of the working size."""
        if scale == 1:
            return self.images[k]
        seq = self.seqs[k]
        small = self._small.get(seq)
        if small is None or small.shape[0] * scale != self.images[k].shape[0]:
            height, width = self.images[k].shape[:2]
            small = cv2.resize(self.images[k], (width // scale, height // scale), interpolation=cv2.INTER_AREA)
            self._small[seq] = small
        return small

    def pairs(self, window: list[int], radius: int) -> list[tuple[int, int]]:
        """Directed edges (positions) inside ``window``: temporal ones (between keyframes that are not landmarks:
        a landmark's neighbours in the list are laps apart) and stored proximity ones."""
        inside = {self.seqs[k]: k for k in window}
        prox = [(inside[a], inside[b]) for a, b in self.proximity if a in inside and b in inside]
        recent = [k for k in window if self.seqs[k] not in self.landmarks]
        return sorted(set(temporal_pairs(recent, radius)) | set(prox))

    def recent(self) -> list[int]:
        """Positions of the keyframes that are not landmarks (the newest ``keep_keyframes``)."""
        return [k for k, seq in enumerate(self.seqs) if seq not in self.landmarks]

    def landmark_positions(self) -> list[int]:
        return [k for k, seq in enumerate(self.seqs) if seq in self.landmarks]

    def linked_landmarks(self, keyframes: list[int]) -> list[int]:
        """Positions of the landmarks with a proximity edge to one of ``keyframes``."""
        inside = {self.seqs[k] for k in keyframes}
        linked = {b for a, b in self.proximity if a in inside} | {a for a, b in self.proximity if b in inside}
        return [k for k in self.landmark_positions() if self.seqs[k] in linked]

    def _window_codes(self, window: list[int], per_edge: bool) -> tuple[torch.Tensor | None, torch.Tensor | None]:
        """The BA problem's codes of keyframes ``window`` (N, h, w, K) and which of them are real (N,) bool (None:
        all); zeros stand in for a keyframe whose codes are still on their way. Its edges keep the fixed kernel
        until they come: the newest keyframe's codes follow its geometry (semantics off the critical path), and a
        background BA that waited for every keyframe's codes ran without ARK all stream long. Not ``per_edge``:
        no codes unless every keyframe has them."""
        have = [self.codes[k] is not None for k in window]
        if not any(have) or not (per_edge or all(have)):
            return None, None
        real = next(self.codes[k] for k, ok in zip(window, have) if ok)
        # stacked channels first and handed over as an (N, h, w, K) view: ARK samples that layout without a copy
        codes = torch.stack([(self.codes[k] if ok else torch.zeros_like(real)).permute(2, 0, 1)
                             for k, ok in zip(window, have)])
        return (codes.to(self.device).permute(0, 2, 3, 1),
                None if all(have) else torch.tensor(have, device=self.device))

    def stacked(self, window: list[int]) -> BAState:
        return BAState(torch.stack([self.poses[k] for k in window]),
                       torch.stack([self.disparity[k] for k in window]), self.intrinsics.clone())

    def run(self, window: list[int], pairs: list[tuple[int, int]], params: BAParams,
            should_stop: Callable[[], bool] | None = None, codes_per_edge: bool = True) -> BAResult | None:
        """BA over the keyframes at positions ``window`` (the first is the gauge) with edges ``pairs``; None (and
        the state unchanged) when the solve failed or its result is implausible. ``should_stop``: see ``run_ba``.
        ``codes_per_edge``: edges between keyframes with codes use ARK though others' codes are not in yet;
        False: codes only once every keyframe of the window has them (:meth:`_window_codes`)."""
        local = {k: n for n, k in enumerate(window)}
        dev = self.device
        ii = torch.tensor([local[a] for a, _ in pairs], dtype=torch.long, device=dev)
        jj = torch.tensor([local[b] for _, b in pairs], dtype=torch.long, device=dev)
        tg = [self.targets(a, b) for a, b in pairs]
        # as DIS gave them (float32): the solve casts them to its compute dtype, and float64 copies of a global
        # BA's were 44 MB at 600 edges. Stacked channels first and handed over as an (E, h, w, 2) view: the
        # solver works in that layout (ba._prepare), which it then takes without a copy of its own
        targets = torch.stack([t.target.permute(2, 0, 1) for t in tg]).to(dev).permute(0, 2, 3, 1)
        conf = torch.stack([t.confidence for t in tg]).to(dev)
        codes, coded = self._window_codes(window, codes_per_edge)
        prior = mask = None
        if params.alpha_disp > 0 and any(self.priors[k] is not None for k in window):
            zero = torch.zeros(self.grid_hw, dtype=torch.float64)
            prior = torch.stack([zero if self.priors[k] is None else self.priors[k] for k in window]).to(dev)
            mask = (prior > 0).to(torch.float64)
        start = self.stacked(window)
        self.jumped_seq = None
        try:
            bounds = (self.focal_range[0] * self.first_focal, self.focal_range[1] * self.first_focal)
            problem = BAProblem(ii, jj, targets, conf, codes, prior, mask, bounds, self.first_principal, coded)
            result = run_ba(start, problem, params, should_stop)
        except (RuntimeError, IndexError) as exc:  # a degenerate window (singular or non-finite): keep its state
            logger.warning("BA failed; window state kept", extra={"keyframes": len(window), "error": str(exc)})
            return None
        if not self._plausible(start, result.state, [self.seqs[k] for k in window], [self.stamps[k] for k in window]):
            logger.warning("BA result rejected (non-finite or a keyframe step jumped); window state kept",
                           extra={"keyframes": len(window), "focal": float(result.state.intrinsics[0])})
            return None
        self._store(window, result, ii, conf)
        return result

    def _plausible(self, start: BAState, state: BAState, window_seqs: list[int], stamps: list[int]) -> bool:
        finite = all(bool(torch.isfinite(t).all()) for t in (state.poses, state.disparity, state.intrinsics))
        if not finite:
            return False
        jumped = self._jumped(start, state, stamps)
        if jumped is not None:
            self.jumped_seq = window_seqs[jumped]
        return jumped is None

    def _jumped(self, start: BAState, state: BAState, stamps: list[int]) -> int | None:
        """A keyframe whose flow constrains nothing (all edges lost) can fly off along the free direction of its
        pose; one such step, kept, would blow up every later constant-velocity prediction. A result is refused
        when the speed over any step between consecutive keyframes (length / time between them) grows beyond
        ``max_step_growth`` times its speed at the start, or the window's median speed where that is higher
        (per step: a whole trajectory's speeds differ by more than that between turning and driving). Speeds,
        not lengths: keyframes come every few frames while the camera turns and every dozen while it only moves
        (hand-held yaw: the steps at the swing's ends are 4x the others', and their BA results were refused).
        Returns the window position of the keyframe that ends the step that grew most, or None."""
        if len(start.poses) < 3:
            return None
        dt = torch.tensor(stamps, dtype=torch.float64, device=start.poses.device).diff().clamp_min(1.0)
        before = (start.poses[1:, :3, 3] - start.poses[:-1, :3, 3]).norm(dim=-1) / dt
        after = (state.poses[1:, :3, 3] - state.poses[:-1, :3, 3]).norm(dim=-1) / dt
        # a speed may grow to max_step_growth x the window's median: under rotation a step that starts near zero
        # legitimately grows (hand-held yaw: 22 of 27 BA results refused). Or its mean (path / time), where that is
        # higher: after a turn on the spot most steps are still, the median is ~0 and refused every result
        floor = max(float(before.median()), float((before * dt).sum() / dt.sum()))
        growth = after / (self.max_step_growth * before.clamp_min(floor))
        # a step shorter than a hundredth of the scene's depth moves no pixel by more than ~f/100 (under a grid
        # px): no jump, however it grew from nothing (a camera turning on the spot: every step starts at 0)
        depth = 1.0 / float(state.disparity.median().clamp_min(1e-12))
        growth = torch.where(after * dt > STILL_STEP * depth, growth, torch.zeros_like(growth))
        return int(growth.argmax()) + 1 if bool((growth > 1).any()) else None

    def _store(self, window: list[int], result: BAResult, ii: torch.Tensor, conf: torch.Tensor) -> None:
        state = result.state
        n = len(window)
        counts = torch.zeros(n, device=ii.device, dtype=conf.dtype).index_add_(0, ii, torch.ones_like(ii, dtype=conf.dtype))
        conf_sum = torch.zeros(n, *conf.shape[1:], device=ii.device, dtype=conf.dtype).index_add_(0, ii, conf)
        mean_conf = conf_sum / counts.clamp_min(1)[:, None, None]
        for n_local, k in enumerate(window):
            self.poses[k] = own_pages_tensor(state.poses[n_local])
            self.disparity[k] = own_pages_tensor(state.disparity[n_local])
            self.static[k] = own_pages_tensor(result.static_weight[n_local].float().cpu())
            self.confidence[k] = own_pages_tensor(mean_conf[n_local].float().cpu())
        self.intrinsics = state.intrinsics
