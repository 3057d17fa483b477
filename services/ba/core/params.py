"""Algorithm parameters of the BA core (frozen dataclasses; the service builds them from its settings)."""
from __future__ import annotations

from dataclasses import dataclass, field, replace

ARK_MODES = ("centred", "paper")  # RobustParams.ark_mode
GRID = 8  # working pixels per grid cell: BA works on the 1/8 grid (docs/CONVENTIONS.md)


@dataclass(frozen=True)
class RobustParams:
    """Barron robust kernel on the flow residual norm, with the ARK per-pixel shape."""

    use_ark: bool = True  # alpha per pixel from code similarity; False: fixed_alpha everywhere
    ark_in_solve: bool = True  # with use_ark, ARK's alpha shapes the solve; False: the solve keeps fixed_alpha
    # and the codes only weigh in on the static weights it reports (what the map leaves out as moving)
    fixed_alpha: float = 2.0  # shape when use_ark is False (2 = L2, 0 = Cauchy, -inf = Welsch)
    alpha_static: float = 2.0  # ARK shape for pixels whose codes agree across views
    alpha_dynamic: float = -2.0  # ARK shape for pixels whose codes disagree (<= 0: heavy tailed)
    kappa: float = 0.5  # cosine similarity at the ARK sigmoid midpoint
    tau: float = 0.05  # ARK sigmoid temperature (cosine units)
    scale: float = 0.5  # Barron scale c, in grid pixels (1/8 of working-resolution pixels)
    ark_refresh_px: float = 0.25  # re-sample an edge's codes for ARK once a reprojection moved this far (grid
    # px) since its last sample; 0 = every iteration (services.ba.core.ark)
    ark_mode: str = "centred"  # shape map from the cosine: "centred" (alpha_static/alpha_dynamic/kappa/tau above,
    # tuned on the centred PCA codes) or "paper" (KM-ViPE's reference map, the paper_* fields below)
    paper_alpha_low: float = -10.0  # "paper": shape at and below paper_floor (heavier than Cauchy)
    paper_alpha_high: float = 2.0  # "paper": shape the ramp tends to at cs = 1 (L2)
    paper_floor: float = 0.4  # "paper": cosine below which the shape is paper_alpha_low
    paper_mid: float = 0.5  # "paper": ramp midpoint, as a fraction of [paper_floor, 1] (cs = 0.7 by default)
    paper_tau: float = 0.1  # "paper": ramp temperature, in the same normalised units

    def __post_init__(self) -> None:
        if self.ark_mode not in ARK_MODES:
            raise ValueError(f"ark_mode must be one of {ARK_MODES}, got {self.ark_mode!r}")
        if not -1 <= self.paper_floor < 1:
            raise ValueError(f"paper_floor must lie in [-1, 1), got {self.paper_floor}")
        if not self.paper_tau > 0 or not self.tau > 0:
            raise ValueError(f"tau and paper_tau must be > 0, got {self.tau}, {self.paper_tau}")
        if not self.paper_alpha_low <= self.paper_alpha_high:
            raise ValueError(f"paper_alpha_low must be <= paper_alpha_high, got {self.paper_alpha_low}, "
                             f"{self.paper_alpha_high}")


@dataclass(frozen=True)
class BAParams:
    """Dense bundle adjustment over keyframe poses, grid disparities and shared intrinsics (the focal length and,
    when asked, the principal point)."""

    iterations: int = 10  # Gauss-Newton/LM iterations per call
    lambda_photo: float = 1.0  # weight of the flow (photometric-style) term
    lambda_embed: float = 0.0  # weight of the embedding residual r = 1 - cs (0 disables it)
    embed_form: str = "angular"  # "angular": r = 1 - cs; "chordal": r = sqrt(2 (1 - cs))
    alpha_disp: float = 0.0  # weight of the disparity prior (d - d_prior)^2 where a prior is given
    optimise_focal: bool = False  # refine the focal length fx (fy keeps its ratio to fx)
    optimise_principal_point: bool = False  # with optimise_focal, refine (cx, cy) too: a lens's centre is off the
    # image centre by up to a few percent, and held at the centre it bends the trajectory (KITTI 07 with its true
    # principal point given: 0.13-0.27 m, at the image centre 0.33 m; docs/BENCHMARKS.md)
    principal_point_sigma: float = 1.0  # grid px: (cx, cy) are pulled to their first guess (BAProblem.principal_point)
    # by a Gaussian prior of this deviation, weighted as one flow residual: a direction the flow leaves open stays
    # at the guess instead of wandering, one the flow constrains is not held
    principal_point_range: float = 0.15  # (cx, cy) stay within this fraction of the grid's width / height of the
    # grid's centre: each step is projected onto it, like the focal's bounds
    fixed_poses: int = 1  # number of oldest window poses held fixed (gauge); >= 1
    fix_scale: bool = True  # without a prior: rescale after each step so |c_1 - c_0| keeps its start value
    lm_init: float = 1e-4  # initial Levenberg-Marquardt damping (relative to the diagonal)
    lm_up: float = 10.0  # damping multiplier after a rejected step
    lm_down: float = 0.3  # damping multiplier after an accepted step
    lm_max: float = 1e6  # stop when the damping grows beyond this (no further decrease possible)
    rel_tol: float = 1e-12  # stop when an accepted step lowers the energy by less than this times the start energy
    pose_eps: float = 1e-9  # absolute damping on pose/focal diagonal (keeps S positive definite)
    disp_eps: float = 1e-6  # absolute damping on disparity diagonal (pixels seen by no edge)
    disp_rel_damping: float = 0.01  # damping of each disparity's relative change, mu (dd / d)^2 on its diagonal, in
    # grid px^2: a pixel's own information is sum w (parallax)^2, so only pixels with under ~0.1 grid px of parallax
    # are held; without it a keyframe that only turned (no baseline) has disparities no flow constrains, BA lets
    # them fly (pure_rotation: median 0.03 -> 50) and the walk after the turn is then explained by depth
    min_disparity: float = 1e-4  # disparities are clamped to at least this after each update
    compute_dtype: str = "float32"  # per-pixel residuals and Jacobians: "float32" (fast) or "float64" (exact
    # to 1e-12, for tests); poses, the camera system and its Cholesky solve are float64 either way
    linearise_edges: int = 48  # a problem with more edges is linearised this many edges at a time, each slice's
    # Jacobians summed into the normal equations and freed, and its residuals and trial energies evaluated a slice
    # at a time (0: all at once): a global BA's Jacobians and their intermediates are ~1 GB at 600 edges. Up to it
    # the Jacobians are kept across a rejected LM step. 48, not 96: lossless KITTI 07's ba peaked 61 MB lower at
    # the same CPU time (docs/BENCHMARKS.md, forty-first session); 32 cost ba 4 % more CPU
    robust: RobustParams = field(default_factory=RobustParams)

    def __post_init__(self) -> None:
        if self.fixed_poses < 1:
            raise ValueError(f"fixed_poses must be >= 1 (gauge), got {self.fixed_poses}")
        if self.compute_dtype not in ("float32", "float64"):
            raise ValueError(f"compute_dtype must be 'float32' or 'float64', got {self.compute_dtype!r}")
        if self.linearise_edges < 0:
            raise ValueError(f"linearise_edges must be >= 0 (0: all edges at once), got {self.linearise_edges}")
        if not self.principal_point_sigma > 0 or not 0 < self.principal_point_range < 0.5:
            raise ValueError(f"principal_point_sigma must be > 0 and principal_point_range in (0, 0.5), got "
                             f"{self.principal_point_sigma}, {self.principal_point_range}")
        if self.embed_form not in ("angular", "chordal"):
            raise ValueError(f"embed_form must be 'angular' or 'chordal', got {self.embed_form!r}")


@dataclass(frozen=True)
class FlowParams:
    """Dense flow targets between keyframe images (OpenCV DIS) and their forward-backward confidence."""

    preset: str = "medium"  # DIS preset: "ultrafast", "fast" or "medium"
    finest_scale: int | None = 0  # DIS finest pyramid level (0 = full resolution; None = the preset's).
    # The medium preset stops at level 1, which measured 2.4% short flow magnitudes on the synthetic world
    # (median |flow| ratio 0.976 vs 0.996 at level 0) and biased BA rotations by ~5%.
    patch_stride: int | None = None  # DIS patch stride in pixels (None = the preset's: 3 for medium). 4 takes 28 %
    # less time for grid targets as close to exact synthetic flow, and KITTI 07 holds (ATE 0.303-0.309 m, ba 78-80
    # -> 70 CPU-s), but TartanAir's bare panelled walls need the denser patches: 2.97 % of path against 1.5 %
    # (2: 1.29 %, +65 % flow time). bench/flow_settings.py, docs/BENCHMARKS.md
    grid: int = 8  # working-resolution pixels per grid cell
    fb_sigma: float = 1.0  # forward-backward error (working px) at which confidence falls to exp(-1/2)
    low_texture_below: float = 7.0  # a pair whose working images show less than this (services.common.image_texture:
    # bare walls; KITTI and the desk show 7.5 and more) ...
    low_texture_patch_stride: int | None = 1  # ... gets DIS patches this dense for its keyframe edges (None: no
    # exception). DIS's patches are what holds a flow where a patch barely constrains it: TartanAir hospital's
    # panelled walls (texture 2.5-6), ATE 0.221 m at stride 3, 0.188 at 2, 0.148 at 1, for 4.5x the flow time there
    # (bench/frontend.py; docs/BENCHMARKS.md). A person passing right in front of the camera is as bare (2.3-4.3)
    # and dense patches give DIS a confident flow of the person's motion: the rule lost the 10,000-frame orbit's map
    # there in the eighteenth session (off since). Keyframes something passing fills now turn back into frames, and
    # a frame's flow keeps the preset's patches (its solve has nothing else to outvote the person): the orbit's
    # frames 2000-2899 0.026 m with the rule, 0.027 m without; 4150-4449 0.022 / 0.024 m (0.048 m with dense
    # frames' flows too); TartanAir 0.89 % of path (1.34 % without; docs/BENCHMARKS.md, twenty-sixth session)

    def is_bare(self, texture: float) -> bool:
        """Whether a pair of images showing ``texture`` (the lower of the two) gets the bare walls' exceptions."""
        return self.low_texture_patch_stride is not None and texture < self.low_texture_below

    def for_texture(self, texture: float) -> "FlowParams":
        """These parameters for a pair of images showing ``texture`` (the lower of the two)."""
        return replace(self, patch_stride=self.low_texture_patch_stride) if self.is_bare(texture) else self
