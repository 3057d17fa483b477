"""The features pipeline as pure state: one frame in, a keyframe or a lite frame out (no transport).

Per frame: resize to the working size, DIS flow against the last keyframe; keyframes also get a depth prior.
That is the geometry, and it leaves at once. Semantics are a separate step on the keyframe
(:meth:`FeaturesCore.describe`: multi-scale DINO features), which the service runs off the frame path; codes
are made by :class:`CodeQueue` once the PCA basis exists (keyframes described before that wait in it).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable, NamedTuple

import numpy as np

from .depth import DepthParams, model_disparity, sensor_disparity
from .geometry import Intrinsics, ResolutionParams, fov_prior, resize_to_working, to_grey, to_rgb, working_size
from .keyframes import KeyframeParams, KeyframeSelector
from .pca import PcaBasis, PcaFitter, PcaParams, project
from .pyramid import PyramidParams, multiscale_features


@dataclass(frozen=True)
class FeaturesParams:
    """Every algorithm parameter of the features service."""

    resolution: ResolutionParams = field(default_factory=ResolutionParams)
    keyframes: KeyframeParams = field(default_factory=KeyframeParams)
    pyramid: PyramidParams = field(default_factory=PyramidParams)
    pca: PcaParams = field(default_factory=PcaParams)
    depth: DepthParams = field(default_factory=DepthParams)
    lite_scale: float = 0.5
    """Side factor of the grey image sent with non-keyframes (relative to the working size)."""


class KeyframeOut(NamedTuple):
    seq: int
    image: np.ndarray
    """(H, W, 3) uint8 RGB working image."""
    intrinsics: Intrinsics
    """At working resolution."""
    features: np.ndarray | None
    """(C, H/8, W/8) float32 unit-norm blended features; None until :meth:`FeaturesCore.describe`."""
    disparity: np.ndarray | None
    """(H/8, W/8) float32 1/m prior, 0 = unknown; None without a depth source."""
    seconds: dict[str, float]
    """Time split: resize, flow, scale_<σ>, depth (pca is added when the codes are made)."""


class LiteOut(NamedTuple):
    seq: int
    grey: np.ndarray
    """(h, w) uint8 grey image at ``lite_scale`` of the working size."""
    intrinsics: Intrinsics
    """For ``grey``."""
    motion_grid_px: float
    seconds: dict[str, float]


class IntrinsicsState:
    """Current intrinsics of the original image: BA's refinement > the user's hint > the FOV prior."""

    def __init__(self, fov_deg: float):
        self.fov_deg = fov_deg
        self._refined: tuple[Intrinsics, int, int] | None = None

    def refine(self, intrinsics: Intrinsics, width: int, height: int) -> None:
        """Intrinsics estimated by ba for a ``width``×``height`` image."""
        self._refined = (Intrinsics(*map(float, intrinsics)), width, height)

    def for_original(self, height: int, width: int, hint: Intrinsics | None) -> Intrinsics:
        if self._refined is not None:
            k, w, h = self._refined
            return k.scaled(width / w, height / h)
        if hint is not None:
            return Intrinsics(*map(float, hint))
        return fov_prior(height, width, self.fov_deg)


class FeaturesCore:
    """Stateful pipeline. ``backbone`` and ``depth_model`` are callables from the model registry."""

    def __init__(
        self,
        params: FeaturesParams,
        backbone: Callable[[np.ndarray], np.ndarray],
        normalise: Callable[[np.ndarray], np.ndarray],
        depth_model: Callable[[np.ndarray], np.ndarray] | None = None,
    ):
        self.params = params
        self.backbone, self.normalise, self.depth_model = backbone, normalise, depth_model
        self.selector = KeyframeSelector(params.keyframes)
        self.intrinsics = IntrinsicsState(params.resolution.fov_deg)
        self.last_lite: tuple[np.ndarray, int, Intrinsics | None, np.ndarray | None] | None = None
        self.n_keyframes = 0

    def process(
        self, seq: int, image: np.ndarray, hint: Intrinsics | None = None, sensor_depth: np.ndarray | None = None
    ) -> KeyframeOut | LiteOut:
        """One frame ((H0, W0) grey or (H0, W0, 3) RGB uint8, original resolution) → keyframe or lite frame."""
        t0 = time.perf_counter()
        size = working_size(image.shape[0], image.shape[1], self.params.resolution)
        work = resize_to_working(to_rgb(image), size)
        grey = to_grey(work)
        t1 = time.perf_counter()
        decision = self.selector.observe(grey)
        t2 = time.perf_counter()
        k_work = self.intrinsics.for_original(image.shape[0], image.shape[1], hint).scaled(size.scale_x, size.scale_y)
        timing = {"resize": t1 - t0, "flow": t2 - t1}
        if not decision.is_keyframe:
            self.last_lite = (image, seq, hint, sensor_depth)
            return self._lite(seq, grey, k_work, decision.motion_grid_px, timing)
        self.last_lite = None
        return self._keyframe(seq, work, k_work, sensor_depth, timing)

    def promote_last(self) -> KeyframeOut | None:
        """On end of stream: the last frame as a keyframe, unless it already was one."""
        if self.last_lite is None:
            return None
        image, seq, hint, depth = self.last_lite
        self.last_lite = None
        size = working_size(image.shape[0], image.shape[1], self.params.resolution)
        work = resize_to_working(to_rgb(image), size)
        self.selector.set_reference(to_grey(work))
        k_work = self.intrinsics.for_original(image.shape[0], image.shape[1], hint).scaled(size.scale_x, size.scale_y)
        return self._keyframe(seq, work, k_work, depth, {"resize": 0.0, "flow": 0.0})

    def _lite(self, seq: int, grey: np.ndarray, k_work: Intrinsics, motion: float, timing: dict) -> LiteOut:
        import cv2

        s = self.params.lite_scale
        h, w = max(8, int(round(grey.shape[0] * s))), max(8, int(round(grey.shape[1] * s)))
        small = cv2.resize(grey, (w, h), interpolation=cv2.INTER_AREA)
        k_small = k_work.scaled(w / grey.shape[1], h / grey.shape[0])
        return LiteOut(seq, small, k_small, motion, timing)

    def _keyframe(self, seq: int, work: np.ndarray, k_work: Intrinsics, depth: np.ndarray | None, timing: dict):
        t0 = time.perf_counter()
        disparity = None
        if depth is not None:
            disparity = sensor_disparity(depth, work.shape[:2], self.params.depth)
        elif self.depth_model is not None:
            patch = int(getattr(self.depth_model, "patch_size", 14))
            disparity = model_disparity(self.normalise(work), self.depth_model, patch, self.params.depth)
        timing["depth"] = time.perf_counter() - t0
        self.n_keyframes += 1
        return KeyframeOut(seq, work, k_work, None, disparity, timing)

    def describe(self, kf: KeyframeOut) -> KeyframeOut:
        """``kf`` with its multi-scale DINO features (the slow step; it touches no state of the frame path, so
        it may run on another thread than :meth:`process`)."""
        pyr = multiscale_features(self.normalise(kf.image), self.backbone, self.params.pyramid)
        seconds = dict(kf.seconds) | {f"scale_{s:g}": t for s, t in pyr.seconds_per_scale.items()}
        return kf._replace(features=pyr.features, seconds=seconds)


class CodeQueue:
    """Holds keyframes until the PCA basis is frozen, then codes them: ``add`` returns what can leave now."""

    def __init__(self, params: PcaParams, backbone: str):
        self.fitter = PcaFitter(params, backbone)
        self.pending: list[KeyframeOut] = []

    def add(self, kf: KeyframeOut) -> tuple[PcaBasis | None, list[tuple[KeyframeOut, np.ndarray]]]:
        """(new basis or None, [(keyframe, (h, w, K) float16 codes)] ready to publish, in order)."""
        new_basis = self.fitter.add(kf.features)
        if self.fitter.basis is None:
            self.pending.append(kf)
            return None, []
        return new_basis, self._code(self.pending + [kf])

    def flush(self) -> tuple[PcaBasis | None, list[tuple[KeyframeOut, np.ndarray]]]:
        """End of stream: fit on what there is and release everything pending."""
        if not self.pending:
            return None, []
        new_basis = self.fitter.fit_now() if self.fitter.basis is None else None
        return new_basis, self._code(self.pending)

    def _code(self, kfs: list[KeyframeOut]) -> list[tuple[KeyframeOut, np.ndarray]]:
        self.pending = []
        out = []
        for kf in kfs:
            t0 = time.perf_counter()
            codes = project(self.fitter.basis, kf.features)
            kf.seconds["pca"] = time.perf_counter() - t0
            out.append((kf, codes))
        return out
