"""Parameters of the BA frontend (graph management, initialisation, motion-only alignment)."""
from __future__ import annotations

from dataclasses import dataclass, field, replace

from services.ba.core.params import BAParams, FlowParams


@dataclass(frozen=True)
class MotionParams:
    """Motion-only (pose-only) Gauss-Newton alignment of a frame to fixed keyframes."""

    iterations: int = 8  # Gauss-Newton iterations at most
    step_tol: float = 1e-3  # ... ended once a step moves the trusted pixels by less than this on average (grid px)
    huber: float = 1.0  # Huber threshold on the flow residual norm (grid px)
    damping: float = 1e-6  # relative Levenberg damping of the 6x6 normal matrix
    min_weight: float = 20.0  # below this total weight (pixel count) the alignment is refused
    flow_downscale: int = 2  # a non-keyframe's flow is computed at 1/this of the working resolution: frames
    # arrive as half-size lite images, so full-resolution flow would only add cost (4x) to upsampled pixels
    max_speed_growth: float = 4.0  # a tracked pose farther from its reference keyframe than this x mapping's speed
    # (Reference.speed) x their time apart is refused for the bounded prediction, as a keyframe's step is
    # (FrontendParams.max_step_growth): PnP on a view the synthetic person fills put frames 17,000 map units away.
    # Mapping bounds a frame's solve the same way against the poses around it (FramePoses._strayed)


@dataclass(frozen=True)
class InitParams:
    """Two-view start of the map once enough keyframes have parallax."""

    min_keyframes: int = 2  # keyframes collected before the first attempt (a live camera waits for the map: two
    # keyframes with parallax start it; KITTI 07 0.327 m vs 0.322 m with 4, synthetic 30 Hz 7 vs 6 mm, bench/frontend.py)
    max_keyframes: int = 6  # after a failed attempt with parallax, keyframes beyond this many slide out (oldest)
    max_pending_frames: int = 100  # frames waiting for a map without parallax beyond this: a static map starts
    min_flow: float = 2.0  # mean grid flow (grid px) between the first and the newest keyframe
    min_parallax_ratio: float = 1.5  # ... of which the flow left after the best rotation must exceed this x the
    # flow's own forward-backward noise (rotation.translates): a turn on the spot moves every pixel but gives no
    # depth (spin: 0.6-0.7; a 4 deg/frame pan moving 0.5 cm/frame 2.3; walking 5 and more)
    min_inliers: int = 50  # essential-matrix inliers required
    ransac_px: float = 1.0  # RANSAC threshold of the essential matrix, working-resolution pixels
    min_confidence: float = 0.5  # flow confidence a grid cell needs to enter the two-view estimate
    iterations: int = 15  # BA iterations over the initial keyframes
    planar_ratio: float = 0.8  # homography inliers >= this x the essential matrix's: a (mostly) planar scene,
    # whose two-view motion is two-fold ambiguous: the start waits for a third keyframe to choose


@dataclass(frozen=True)
class RelocaliseParams:
    """A keyframe's pose from ORB features and PnP against the keyframe before it, when the flow from its motion
    prediction barely supports the pose (a lost view, a whip pan): services.ba.frontend.relocalise."""

    below_share: float = 0.3  # mapping tries the PnP start (0: never) when its alignment keeps less than this share of the
    # grid cells (the synthetic orbit: 0.70-0.98 per keyframe, the keyframe after a 20-frame blank 0.09)
    track_below_share: float = 0.15  # tracking tries it from a frame it could not track until a frame's flow
    # from the prediction keeps this share again (KITTI 07: 1 % of frames below; the synthetic orbit's frames
    # 30+ frames from their reference after a blank: 0.04-0.07); 0: never
    features: int = 1500  # ORB keypoints per image
    ratio: float = 0.8  # Lowe's ratio test on the two nearest Hamming matches
    reprojection_px: float = 3.0  # PnP RANSAC inlier threshold, working pixels
    min_inliers: int = 30  # fewer: no pose (a view that shares too little with the keyframe)
    iterations: int = 500  # RANSAC iterations


@dataclass(frozen=True)
class GraphParams:
    """Edges of the keyframe graph."""

    window: int = 25  # keyframes in the sliding window (the oldest one is the gauge)
    temporal_radius: int = 2  # temporal edges connect keyframes at most this far apart (both directions)
    proximity_max_flow: float = 10.0  # candidate proximity edge: mean induced flow below this (grid px)
    proximity_overlap: float = 0.25  # a candidate that turned on the spot (no baseline for its depth) and that only
    # its rotation puts beyond proximity_max_flow is judged by the flow its depth causes (edges.flow_parts) where at
    # least this share of its pixels land in the new keyframe (0: always by the whole induced flow)
    proximity_max_edges: int = 3  # proximity edges added per new keyframe
    proximity_nms: int = 2  # a chosen proximity edge suppresses candidates this close in keyframe index
    loop_max_edges: int = 1  # proximity edges from a new keyframe to held keyframes older than the window (0: none;
    # upkeep.add_loop_edges), chosen as proximity_pairs chooses, where ...
    loop_overlap: float = 0.5  # ... at least this share of the old keyframe's pixels land in the new one, ...
    loop_every: int = 4  # ... and none of the keyframes this close before it got one
    landmark_overlap: float = 0.7  # a keyframe leaving the held ones stays as a landmark unless a landmark has this
    # share of its pixels land in it with less than proximity_max_flow (upkeep.new_place)
    remove_max_flow: float = 1.0  # the newest keyframe is redundant when its flow to the previous is below this
    global_radius: int = 3  # temporal radius of the global BA's own edge set


@dataclass(frozen=True)
class FrontendParams:
    """Everything the frontend needs; the service builds it from its settings."""

    graph: GraphParams = field(default_factory=GraphParams)
    init: InitParams = field(default_factory=InitParams)
    motion: MotionParams = field(default_factory=MotionParams)
    relocalise: RelocaliseParams = field(default_factory=RelocaliseParams)
    ba: BAParams = field(default_factory=lambda: BAParams(iterations=3, optimise_focal=True,
                                                          optimise_principal_point=True))  # per new keyframe
    global_ba: BAParams = field(default_factory=lambda: BAParams(iterations=10, optimise_focal=True,
                                                                 optimise_principal_point=True))  # end
    global_ba_s: float = 0.0  # the end-of-stream BA stops before an iteration that would end past this many
    # seconds (refinement.time_bound; 0: runs its iterations): end-of-stream work bounded by time, whatever the window holds
    background_ba_every: int = 10  # a lossless stream's mapping, when idle, runs the end-of-stream BA over every
    # held keyframe once this many keyframes have joined since the last (0: never; Frontend.refine_globally)
    background_ba_s: float = 3.0  # ... within this many seconds (refinement.time_bound)
    live_background_ba_s: float = 0.6  # a real-time stream's mapping runs the same BA when it is due and mapping
    # is idle, within this many seconds (0: never): keyframes arrive every ~0.2 s on KITTI, and a 1.6-2.2 s BA left
    # mapping behind them (first poses 1.34-2.32 m against 1.45-1.66 m); at 0.6 s it does 2-3 iterations over 30-60
    # keyframes and the live map drifts less (KITTI 07 first poses ~1.5 -> ~1.1 m; docs/BENCHMARKS.md)
    background_ba_keyframes: int = 60  # ... over this many keyframes, the newest held ones and the landmarks they
    # reach (0: keep_keyframes; Refinement._background_span). Within its time bound a slow machine takes 3-4 steps
    # over 60, fewer over every held one: KITTI 07 lossless 0.27-0.32 m over all, 0.17-0.20 m over 60, 0.15-0.16 m
    # over 40, but TartanAir in process 0.88-1.00 % of path over all or 60, 1.18-1.27 % over 40 (docs/BENCHMARKS.md)
    background_ba_edges: int = 0  # ... and at most this many edges (0: no bound but the keyframes';
    # Refinement._background_span): its memory grows with its edges (~0.4 MB each). Off by default: at 588 (100
    # keyframes in a row at radius 3) a 10,000-frame orbit's live poses were 1.70 m off over 5,389 frames against
    # 0.58 m, and ba's service high-water no lower (docs/BENCHMARKS.md)
    settled_global_ba_s: float = 2.0  # once background BAs ran, the end-of-stream BA stays within this many
    # seconds (0: global_ba_s alone bounds it): they gave every held keyframe its iterations
    # during the stream, so the end only settles the newest (a lossless 2,000-frame room orbit: 24 s otherwise;
    # at 2 s its final ATE is 0.079 m against 0.076 at 5 s, one run each, docs/BENCHMARKS.md)
    settle_all_keyframes: bool = False  # True: the end-of-stream BA spans every held keyframe even after background
    # BAs; False: the keyframes since the last background BA and a window before them (Refinement._settle_span)
    realign_focal_change: float = 0.05  # end of stream: frames aligned under a focal this far (relative) from the
    # final one are aligned again with their flow (a frame's relative pose is solved on one camera model)
    final_align_s: float = 8.0  # at end of stream, frames posed without mapping's own flow (tracked on a live
    # stream, or interpolated by time) are aligned again to their final keyframes, oldest first, for at most this
    # long: tracking's cheap flow leaves them ~2 cm off on the synthetic world where keyframes are at 3 mm
    flow: FlowParams = field(default_factory=FlowParams)
    focal_restarts: tuple[float, ...] = (0.7, 1.0, 1.4)  # at focal_after keyframes the map starts again from
    # these x the focal guess, focal free; the lowest BA cost is kept (start.calibrate_focal)
    live_focal_restarts: tuple[float, ...] = (0.7, 1.4)  # a live stream's calibration skips the restart from the
    # guess itself (the map as it is started there): mapping stalls for it, ~1 s per restart on this CPU
    focal_after: int = 6  # the focal length is refined once the window holds this many keyframes
    ark_with_focal: bool = False  # BAs that refine the focal solve with ARK where codes are in; False: with the
    # fixed kernel until the focal is frozen, the codes still giving the static weights (a stream's first codes
    # come late and in a young, refitted PCA basis: KITTI 07 through the pipeline, focal +0.94 % with ARK,
    # -0.28 % without; docs/BENCHMARKS.md)
    window_ark_per_edge: bool = False  # a keyframe's window BA uses ARK on the edges whose codes are in even while
    # the newest keyframe's are on their way (its codes follow its geometry); False: only once every keyframe of
    # the window has codes. The window BA is mapping's critical path: per edge it cost lossless KITTI 07 15 % of
    # ba's CPU (3.15 -> 2.65 fps) for the same ATE; background and end-of-stream BAs use codes per edge always
    # (KeyframeGraph.run), so every keyframe is refined with ARK once its codes are in (docs/BENCHMARKS.md)
    focal_until: int = 30  # ... and frozen after this many keyframes: under long forward motion focal and depth
    # trade off, and the focal drifts (KITTI 07: 455 -> 371 working px over frames 60-100 when never frozen)
    max_step_growth: float = 4.0  # BA results whose longest keyframe step grows beyond this x the start's are refused
    predict_flow: bool = True  # after the start, DIS flow targets begin at the flow the current state induces
    keep_keyframes: int = 100  # keyframes held (window + the ones before it that proximity edges and the end-of-
    # stream BA still use); older ones leave the graph with their frames, so memory does not grow with the stream.
    # KITTI 07 (90 keyframes): end-of-stream BA over all of them gives ATE 0.32 m, over the last 40 0.63 m
    # (bench/frontend.py; docs/BENCHMARKS.md)
    landmark_keyframes: int = 64  # keyframes leaving the held ones that show a place no landmark shows stay, up to
    # this many (0: none), fixed, as loop edges' targets: later laps tie to the first instead of to the lap before,
    # whose drift they share (Frontend._retire; KeyframeGraph.landmarks)
    keyframe_flow_downscale: int = 2  # a lossless stream's keyframe edge flows at 1/this of the working size: 4x
    # less DIS (lossless KITTI 07 end to end 2.3 -> 3.3 fps, ATE 0.138 -> 0.137 m; a fast, densely keyframed orbit
    # loses more: tests/test_landmarks.py's 0.10 -> 0.16 m, 1 keeps it; docs/BENCHMARKS.md). Pairs where half-size flow
    # loses what carries the estimate keep the working size (KeyframeGraph._flow_scale): bare ones, and ...
    full_size_below_parallax: float = 2.0  # ... those whose predicted translational parallax (median, working px)
    # is under this: a pair that only turned, or starts moving again after a turn, has depth and translation in
    # flow differences of a pixel or less (the synthetic pure rotation at half size: 1.64 % of path, 0.53 % with
    # this; KITTI 07 keeps 270 of its 271 pairs at half size). 0: no such exception
    live_flow_downscale: int = 2  # keyframes of a real-time stream get their edge flows at 1/this of the working
    # size (DIS 52 -> 12 ms per flow on KITTI): a live camera's mapping must keep up with its keyframes
    live_flow_preset: str = "ultrafast"  # DIS preset of a real-time stream's keyframe edge flows: 10.6 ms per
    # KITTI flow at half the working size against medium's 25 ms (one thread); bench/frontend.py --track --live
    # --map-lag 2 on KITTI 07: edge flows 18.7 -> 7.7 s, ATE 0.437 -> 0.481 m
    live_iterations: int = 3  # LM iterations of the window BA per real-time keyframe
    weak_keyframe_gap: float = 2.0  # a keyframe its flow barely supports (less than relocalise.below_share of the
    # grid, or an implausible step) right after well-supported ones becomes a frame again while it comes within
    # this x the recent keyframe spacing of the keyframe before (Frontend._lost_support): such keyframes come every
    # frame while something fills the view (the synthetic person), their flows are of its motion, and in the
    # window BA they broke the map's scale; 0: never
    burst_gap: float = 0.5  # a keyframe that comes within this x the median spacing of the six keyframes before it
    # becomes a frame again, whatever its flow's support (Frontend._in_burst): a rigid thing filling the view (the
    # 3,000-frame world's person, its flow supported by 47-79 % of the grid) makes keyframes a frame apart where
    # they came 8-10 apart, and as the window's oldest, its gauge, they broke the map (frames 1100-1499 in one
    # process: 0.12-2.09 m ATE off, 0.19 m at 0.34, 0.044 m at 0.5, three runs each; docs/BENCHMARKS.md). A camera
    # that speeds up still gets a keyframe at this share of the spacing, which then adapts within a few
    # keyframes; 0: never
    live_max_deferred: int = 3  # a keyframe may leave its window BA to a later one (KeyframeInput.defer_ba) at
    # most this many times in a row
    live_window: int = 16  # keyframes in a real-time stream's sliding window: BA cost grows with the window's
    # edges (bench/ba.py: 0.13 s for 10 keyframes, 0.35 s for 25), and mapping that falls behind a camera leaves
    # tracking on a keyframe ever further back; the end-of-stream BA still spans every held keyframe. 16, not 12:
    # KITTI 07 live 0.37-0.41 m against 0.37-0.44 m and focal -0.2 to -0.5 % against -1.2 to -1.5 %, for ~10 %
    # more window BA time (docs/BENCHMARKS.md)
    live_calibration: str = "when_undetermined"  # a real-time stream's focal restarts (focal_after keyframes):
    # "always" as a lossless stream, or only "when_undetermined" (the map as it is ends its BA at a focal bound),
    # since each restart stalls mapping (KITTI 07, 2 cores: 8 s of stall and 44 keyframes queued behind it)
    focal_range: tuple[float, float] = (0.36, 1.75)  # BA keeps the focal inside this x the first guess (60 deg
    # across the longer side): 115 deg to 36 deg, so 40-110 deg cameras fit. A bound constrains the focal; it never
    # throws a BA result away (the old refusal outside 0.6-1.6 x refused TartanAir's true 90 deg focal, 0.58 x)


def focal_ba(ba: BAParams, params: FrontendParams) -> BAParams:
    """``ba`` refining the focal: solved with ARK only where ``params.ark_with_focal``, else with the fixed kernel
    (ARK's codes still give the static weights)."""
    ba = replace(ba, optimise_focal=True)
    return ba if params.ark_with_focal else replace(ba, robust=replace(ba.robust, ark_in_solve=False))
