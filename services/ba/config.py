"""Settings of the BA service (``KMVIPE_BA_*`` environment variables, or ``[ba]`` of the ``KMVIPE_CONFIG`` file),
built once per process.

The algorithm parameters are turned into the frozen dataclasses of :mod:`services.ba.core.params`, which the
math core takes; the core never reads settings itself.
"""
from __future__ import annotations

from typing import Literal

import torch
from pydantic import Field
from pydantic_settings import SettingsConfigDict

from services.ba.core.params import BAParams, FlowParams, RobustParams
from services.common.config_file import KmVipeSettings
from services.common.keys import ALL_STREAMS


class BASettings(KmVipeSettings):
    """Dense BA service settings."""

    # "none" in the environment is None: the patch strides' way to say "no exception" / "the preset's own"
    model_config = SettingsConfigDict(env_prefix="KMVIPE_BA_", env_file=".env", extra="ignore",
                                      env_parse_none_str="none")

    stream: str = ALL_STREAMS
    """The stream served (``kmvipe/<stream>/...``); ``*``: every stream a source announces, each with its own state
    (services/common/streams.py; replicas split them by ``KMVIPE_SHARD_*``)."""
    device: str = "auto"
    """``auto`` (CUDA when available, else CPU), ``cpu`` or ``cuda[:n]``."""
    window: int = 25
    """Keyframes in the frontend sliding window."""
    temporal_radius: int = 2
    """Temporal edges connect keyframes at most this far apart in the window."""
    iterations: int = 6
    """LM iterations per frontend update."""
    global_iterations: int = 10
    """LM iterations of the global BA (at the end of stream, and in mapping's spare time on lossless streams)."""
    global_rel_tol: float = 1e-4
    """The global BA stops once an accepted step lowers the energy by less than this times its start energy: after
    the BAs of mapping's spare time it starts near its optimum (KITTI 07 lossless, bench/frontend.py: end of stream
    16.5 -> 7.1 s, ATE 0.315 -> 0.309 m with both; this alone 14.9 s, 0.315 m)."""
    optimise_focal: bool = True
    """Refine the shared focal length (published on ``intrinsics``)."""
    optimise_principal_point: bool = True
    """Refine the principal point (cx, cy) wherever the focal is refined (``BAParams.optimise_principal_point``):
    KITTI 07 0.31 -> 0.14 m, TartanAir 0.98 -> 0.76 % of path, at a focal further from the truth where the map's
    flow wants one (KITTI -2.2 %, the desk +3.0 %; docs/BENCHMARKS.md)."""
    principal_point_sigma: float = Field(BAParams.principal_point_sigma, gt=0)
    """Grid px: the Gaussian prior that holds the principal point at its first guess (the image centre, or the
    calibration hint), weighted as one flow residual (``BAParams.principal_point_sigma``)."""
    principal_point_range: float = Field(BAParams.principal_point_range, gt=0, lt=0.5)
    """The principal point stays within this fraction of the image's width / height of its centre."""
    lambda_embed: float = 0.0
    """Weight of the code-similarity residual (0 disables the term)."""
    embed_form: Literal["angular", "chordal"] = "angular"
    """``angular``: r = 1 - cs; ``chordal``: r = sqrt(2 (1 - cs))."""
    alpha_disp: float = 0.05
    """Weight of the disparity prior where the features service sends a depth prior."""
    disp_rel_damping: float = BAParams.disp_rel_damping
    """LM damping of each disparity's relative change (grid px^2): holds the depth of pixels no flow constrains,
    such as a keyframe that only turned (``BAParams.disp_rel_damping``; 0 disables it)."""
    use_ark: bool = True
    """Adaptive robust kernel from code similarity; false = fixed ``fixed_alpha`` everywhere."""
    fixed_alpha: float = 2.0
    """Barron shape without ARK (2 = L2, 0 = Cauchy)."""
    alpha_static: float = 2.0
    """ARK shape of consistent pixels."""
    alpha_dynamic: float = -2.0
    """ARK shape of inconsistent pixels (<= 0)."""
    kappa: float = 0.5
    """ARK sigmoid midpoint (cosine similarity)."""
    tau: float = 0.05
    """ARK sigmoid temperature."""
    robust_scale: float = 0.5
    """Barron scale c in grid pixels."""
    ark_refresh_px: float = 0.25
    """Re-sample an edge's codes for ARK once one of its reprojections moved this far (grid px); 0 = every
    iteration (RobustParams.ark_refresh_px)."""
    compute_dtype: Literal["float32", "float64"] = "float32"
    """Per-pixel BA arithmetic; the camera system is float64 either way (docs/BENCHMARKS.md, BA core)."""
    linearise_edges: int = Field(BAParams.linearise_edges, ge=0)
    """A BA over more edges than this forms its Jacobians this many edges at a time (0: all at once), which
    bounds the memory of the end-of-stream BA over every held keyframe (docs/BENCHMARKS.md, BA memory)."""
    flow_preset: Literal["ultrafast", "fast", "medium"] = "medium"
    """OpenCV DIS preset of the flow targets."""
    flow_patch_stride: int | None = Field(FlowParams.patch_stride, ge=1)
    """OpenCV DIS patch stride of the flow targets and of tracking's flow (None: the preset's own, 3 for medium). 4
    saves a tenth of ba's time on driving footage but loses bare walls (``FlowParams.patch_stride``)."""
    flow_low_texture_patch_stride: int | None = Field(FlowParams.low_texture_patch_stride, ge=1)
    """DIS patch stride of the edge flows of keyframe pairs that show less than texture 7 (None: the same as every
    pair). 1 holds bare walls (TartanAir hospital 1.34 → 0.89 % of path); frames' flows keep the preset's, since a
    bare object that fills the view (a person right in front of the camera) is followed by dense patches
    (``FlowParams.low_texture_patch_stride``). ``none`` turns the rule off."""
    fb_sigma: float = 1.0
    """Forward-backward error (working px) where flow confidence is exp(-1/2)."""

    def robust_params(self) -> RobustParams:
        """The robust-kernel parameters of the core."""
        return RobustParams(use_ark=self.use_ark, fixed_alpha=self.fixed_alpha, alpha_static=self.alpha_static,
                            alpha_dynamic=self.alpha_dynamic, kappa=self.kappa, tau=self.tau,
                            scale=self.robust_scale, ark_refresh_px=self.ark_refresh_px)

    def ba_params(self, global_ba: bool = False) -> BAParams:
        """BA parameters of the frontend (or, with ``global_ba``, of the background global BA)."""
        return BAParams(iterations=self.global_iterations if global_ba else self.iterations,
                        rel_tol=self.global_rel_tol if global_ba else BAParams.rel_tol,
                        lambda_embed=self.lambda_embed, embed_form=self.embed_form, alpha_disp=self.alpha_disp,
                        disp_rel_damping=self.disp_rel_damping,
                        optimise_focal=self.optimise_focal, optimise_principal_point=self.optimise_principal_point,
                        principal_point_sigma=self.principal_point_sigma,
                        principal_point_range=self.principal_point_range, robust=self.robust_params(),
                        compute_dtype=self.compute_dtype, linearise_edges=self.linearise_edges)

    def flow_params(self) -> FlowParams:
        """Flow-target parameters."""
        return FlowParams(preset=self.flow_preset, fb_sigma=self.fb_sigma, patch_stride=self.flow_patch_stride,
                          low_texture_patch_stride=self.flow_low_texture_patch_stride)

    def torch_device(self) -> torch.device:
        """Resolve ``device`` (``auto`` picks CUDA when present)."""
        if self.device == "auto":
            return torch.device("cuda" if torch.cuda.is_available() else "cpu")
        return torch.device(self.device)
