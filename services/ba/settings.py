"""Deployment settings of the BA service (``KMVIPE_BA_*``, or ``[ba]`` of the ``KMVIPE_CONFIG`` file), built once per
process.

The BA-core fields (robust kernel, iterations, flow preset, ...) come from :class:`services.ba.config.BASettings`;
this class adds the service and frontend ones and turns everything into :class:`FrontendParams`.
"""
from __future__ import annotations

import dataclasses
import functools
from typing import TYPE_CHECKING, Callable, Literal

from pydantic import Field
from pydantic_settings import SettingsConfigDict

from services.ba.core.params import FlowParams

from services.ba.config import BASettings
from services.ba.frontend.params import FrontendParams, GraphParams, InitParams, MotionParams, RelocaliseParams

if TYPE_CHECKING:  # both import torch: only where a tracker is made
    from services.ba.frontend.tracker import Tracker
    from services.ba.tracking_process import LocalTracker, TrackerProcess


class BaSettings(BASettings):
    """BA service settings: the core's plus stream, threads and frontend graph management."""

    model_config = SettingsConfigDict(env_prefix="KMVIPE_BA_", env_file=".env", extra="ignore")

    threads: int = 1
    """CPU threads for torch. One: ba shares the 2 reference cores with features, and there two threads measured
    slower than one (1.71 vs 0.49 s per iteration at 25 keyframes, docs/BENCHMARKS.md)."""
    iterations: int = 3
    """LM iterations of the window BA per new keyframe (KITTI 07: 3 and 4 both give ATE 0.324 m; 3 keeps a
    25-keyframe window under 0.3 s per keyframe, docs/BENCHMARKS.md)."""
    global_iterations: int = 20
    """LM iterations of the end-of-stream global BA (KITTI 07: 0.300 m at 20, 0.301 m at 10, 0.397 m at 5, each
    ~0.23 s over its 90 keyframes; TartanAir hospital: 0.266 m at 20, 0.361 m at 10)."""
    fixed_alpha: float = 0.0
    """Barron shape without codes: Cauchy (KITTI 07, 60 frames: ATE 1.37 m with L2, 0.34 m with Cauchy, c = 0.2)."""
    alpha_static: float = 0.0
    """ARK shape of consistent pixels: Cauchy too, since DIS flow has outliers on static content as well."""
    robust_scale: float = 0.2
    """Barron scale c in grid pixels."""
    ark_with_focal: bool = FrontendParams.ark_with_focal
    """BAs that refine the focal (up to ``focal_until`` keyframes) solve with ARK where codes are in; false: with
    the fixed kernel until the focal is frozen (the codes still give the static weights)."""
    window_ark_per_edge: bool = FrontendParams.window_ark_per_edge
    """A keyframe's window BA uses ARK on the edges whose codes are in while the newest keyframe's are on their
    way; false: only once the whole window has codes (background and end-of-stream BAs always go per edge)."""
    focal_until: int = FrontendParams.focal_until
    """Freeze the focal length after this many keyframes."""
    init_keyframes: int = InitParams.min_keyframes
    """Keyframes collected before the two-view start is tried."""
    init_max_keyframes: int = InitParams.max_keyframes
    """After a failed two-view start with parallax, keyframes beyond this many slide out (oldest first)."""
    init_min_flow: float = InitParams.min_flow
    """Mean grid flow (grid px) between the first and newest keyframe needed to start."""
    proximity_max_flow: float = GraphParams.proximity_max_flow
    """Proximity-edge candidates: induced flow below this (grid px)."""
    proximity_overlap: float = GraphParams.proximity_overlap
    """A proximity-edge candidate that turned on the spot and that only its rotation puts beyond
    ``proximity_max_flow`` is judged by the flow its depth causes (the rotation is predicted) where at least this
    share of its pixels land in the new keyframe; 0: always by the whole induced flow."""
    proximity_max_edges: int = GraphParams.proximity_max_edges
    """Proximity edges per new keyframe."""
    loop_max_edges: int = GraphParams.loop_max_edges
    """Loop edges per new keyframe: to held keyframes older than the window that it sees again (0: none); only the
    BAs over every held keyframe use them."""
    loop_every: int = GraphParams.loop_every
    """A keyframe gets loop edges only when none of the keyframes this close before it got one."""
    remove_max_flow: float = GraphParams.remove_max_flow
    """A second-newest keyframe whose flow to its predecessor is below this (grid px) is removed."""
    global_radius: int = GraphParams.global_radius
    """Temporal radius of the end-of-stream global BA."""
    focal_after: int = FrontendParams.focal_after
    """Refine the focal length once the window holds this many keyframes."""
    motion_huber: float = MotionParams.huber
    """Huber threshold of motion-only alignment (grid px)."""
    keep_keyframes: int = FrontendParams.keep_keyframes
    """Keyframes held in memory; older ones leave with their frames (their last published poses are final)."""
    landmark_keyframes: int = Field(FrontendParams.landmark_keyframes, ge=0)
    """Keyframes leaving the held ones that show a place no landmark shows stay as landmarks, up to this many (0:
    none): fixed targets of loop edges, so that a camera that comes back ties to its first visit."""
    landmark_overlap: float = Field(GraphParams.landmark_overlap, gt=0, le=1)
    """A leaving keyframe is a new place unless a landmark has this share of its pixels land in it."""
    realtime_defer_backlog: int = 1
    """Real-time streams: when this many keyframes wait for mapping, the next one is only aligned and joins the
    graph, its window BA left to a later keyframe (at most ``live_max_deferred`` in a row); every keyframe stays in
    the graph, so keyframes stay close enough for their flow."""
    live_max_deferred: int = FrontendParams.live_max_deferred
    """Real-time streams: keyframes in a row that may leave their window BA to a later one."""
    realtime_keyframe_backlog: int = 64
    """Real-time streams: when this many keyframes wait for mapping, the oldest is merged into the map as a
    frame (posed, not a BA keyframe) instead of queueing without bound. Lossless streams map every keyframe.
    Merging is the last resort: a keyframe merged leaves its neighbours twice as far apart for DIS, and on KITTI 07
    at 10 Hz on 2 cores merging from 24 queued broke the map (8-28 m), while queueing up to 55 ended at 0.46-0.67 m."""
    realtime_max_merged: int = 1
    """At most this many keyframes in a row are merged; then one is mapped whatever the backlog."""
    keyframe_flow_downscale: int = Field(FrontendParams.keyframe_flow_downscale, ge=1, le=4)
    """Lossless streams: keyframe edge flows at 1/this of the working size. 2 (default): 4x less DIS, lossless
    KITTI 07 end to end 2.3 -> 3.3 fps at the same ATE; bare pairs and pairs with little parallax keep the working
    size. 1: every edge flow at the working size, for the last centimetres over the rate (a fast, densely
    keyframed orbit: 0.16 -> 0.10 m; docs/BENCHMARKS.md)."""
    full_size_below_parallax: float = Field(FrontendParams.full_size_below_parallax, ge=0)
    """Lossless streams with ``keyframe_flow_downscale`` > 1: a keyframe pair whose poses predict less translational
    parallax than this (median, working px) gets its flows at the working size: a camera that turns on the spot,
    or starts moving after a turn, has its depth and translation in flow differences of a pixel or less (0: no such
    exception)."""
    live_flow_downscale: int = FrontendParams.live_flow_downscale
    """Real-time streams: keyframe edge flows at 1/this of the working size (mapping keeps up with a live camera)."""
    live_iterations: int = FrontendParams.live_iterations
    """Real-time streams: LM iterations of the window BA per keyframe."""
    background_ba_every: int = FrontendParams.background_ba_every
    """Mapping's spare time runs the global BA over every held keyframe once this many keyframes have joined since
    the last (0: only at the end of stream); on a real-time stream bounded to ``live_background_ba_s``."""
    background_ba_s: float = FrontendParams.background_ba_s
    """... within this many seconds (it stops before an iteration that would end past them)."""
    live_background_ba_s: float = Field(FrontendParams.live_background_ba_s, ge=0)
    """Real-time streams: the same BA in mapping's spare time, within this many seconds (0: never). Short, since
    keyframes keep arriving: a few iterations that keep the live map's drift down."""
    background_ba_keyframes: int = FrontendParams.background_ba_keyframes
    """... over this many keyframes, the newest held ones and the landmarks they reach counted together (0:
    ``keep_keyframes``): the BA's memory and time grow with its keyframes' edges, and within its time bound a wider
    span gets fewer steps."""
    background_ba_edges: int = FrontendParams.background_ba_edges
    """... and at most this many edges, the oldest keyframes left out until it fits (0: no bound but the
    keyframes'): loop edges cost memory like any other (588 is what 100 keyframes in a row have at radius 3)."""
    background_ba_when_busy: bool = True
    """Lossless streams: the global BA also runs when it is due and keyframes wait (ba sets a lossless stream's
    pace: with no spare time it would never run, and the end of stream would do all of it)."""
    settled_global_ba_s: float = FrontendParams.settled_global_ba_s
    """Once background global BAs ran, the end-of-stream BA stays within this many seconds (0: only ``global_ba_s``
    bounds it)."""
    settle_all_keyframes: bool = FrontendParams.settle_all_keyframes
    """Once background global BAs ran, the end-of-stream BA still spans every held keyframe (True), or only those
    since the last background BA and a window before them (False)."""
    live_flow_preset: Literal["ultrafast", "fast", "medium"] = FrontendParams.live_flow_preset
    """Real-time streams: OpenCV DIS preset of keyframe edge flows."""
    live_window: int = FrontendParams.live_window
    """Real-time streams: keyframes in the sliding window BA (lossless streams: ``window``)."""
    live_calibration: Literal["always", "when_undetermined"] = FrontendParams.live_calibration
    """Real-time streams: the focal restarts run always, or only when the map's own BA ends at a focal bound."""
    mapping_min_seconds: float = 0.0
    """Each keyframe's mapping takes at least this long: a slow CPU on demand (tests of back-pressure)."""
    tracking_backlog: int = 3
    """Real time: frames waiting for tracking beyond this many drop the oldest (mapping still poses them by
    interpolation), so a frame's pose never lags the camera by more than a few frames. Lossless never drops."""
    tracking_flow_preset: str = "medium"
    """DIS preset of frame-rate tracking, at the preset's own finest scale (1 for medium): 13 ms per KITTI frame
    pair (half working size, both directions) against 53 ms at full scale as the window uses it; on the synthetic
    world 5 frames from the reference 1.2 cm / 0.16 deg against 0.7 cm / 0.06 deg (fast: 11 ms, 1.4 cm / 0.17 deg)."""
    tracking_finest_scale: int | None = None
    """DIS finest pyramid level of tracking's flow (None: the preset's own, 1 for medium)."""
    tracking_promote_after: int = 1
    """Tracking keeps mapping's reference while it is at most this many keyframes behind the newest keyframe;
    further behind, tracking promotes its own keyframes (depth carried over) and corrects them by mapping's."""
    tracking_process: bool = True
    """Frame-rate tracking in a child process of its own (its own interpreter: it never waits for mapping's BA,
    and mapping gets the second core); False: a thread of the ba process, sharing mapping's interpreter."""
    relocalise_below_share: float = RelocaliseParams.below_share
    """Mapping aligns a keyframe again from a PnP pose (ORB against the keyframe before it) when the flow from its
    prediction keeps less than this share of the grid (0: never); see frontend/relocalise.py."""
    tracking_relocalise_below_share: float = RelocaliseParams.track_below_share
    """Tracking tries a PnP pose from a frame it could not track (a lost view) until its prediction's flow keeps
    this share of the grid again; 0: never."""
    weak_keyframe_gap: float = FrontendParams.weak_keyframe_gap
    """A keyframe whose flow supports less than ``relocalise_below_share`` of the grid (or whose step is refused),
    right after keyframes supported by more than twice that, becomes a frame again while it comes within this x the
    recent keyframe spacing (0: never)."""
    burst_gap: float = FrontendParams.burst_gap
    """A keyframe that comes within this x the median spacing of the six keyframes before it becomes a frame again,
    whatever its flow's support: something filling the view makes keyframes a frame apart (0: never)."""
    tracking_max_speed_growth: float = MotionParams.max_speed_growth
    """Tracking refuses a pose farther from its reference than this x mapping's keyframe speed x their time apart
    (the prediction is kept); 0 or less: no bound."""
    tracking_nice: int = 0
    """Niceness of the tracking thread (Linux; per thread). Tracking comes first on a shared CPU."""
    mapping_nice: int = 5
    """Niceness of the mapping thread: behind tracking, ahead of the semantics backbone (features' ``semantics_nice``)."""
    switch_interval_s: float = Field(0.0005, gt=0)
    """Python's thread switch interval in the ba process (``sys.setswitchinterval``; Python's default is 5 ms).
    Tracking and mapping share one interpreter, and a frame's tracking takes the interpreter hundreds of times:
    each wait of up to one interval adds to its latency (KITTI 07 live, 2 cores: p99 789 ms at 5 ms, 308 ms at
    0.5 ms in back-to-back runs)."""
    eos_wait_s: float = 30.0
    """How long features' end of stream waits for keyframes it announced that have not arrived."""
    inbox_size: int = 4096
    """Messages buffered between the bus and the service loop."""
    checkpoint_dir: str = ""
    """Where each stream's mapping state is checkpointed (one file per stream and session), so a ba killed
    mid-stream resumes in the same world frame; "" (``kmvipe run``): none. Compose and Kubernetes set a volume."""
    checkpoint_period_s: float = 2.0
    """At most one checkpoint per this many seconds (each is written after a keyframe's BA)."""
    refine_frames_per_idle: int = 1
    """Live streams: when mapping has nothing queued, up to this many frames that tracking posed are aligned again
    with mapping's own flow before it looks at its inbox again (0: never; the end of stream still does)."""
    global_ba_s: float = FrontendParams.global_ba_s
    """The end-of-stream BA stops before an iteration that would end past this many seconds (0: all
    ``global_iterations``), so the end of a stream is bounded in time whatever the window holds."""
    final_align_s: float = FrontendParams.final_align_s
    """End of stream: how long frames still posed by tracking alone are aligned again with mapping's flow."""
    release_memory_period_s: float = 10.0
    """At most once per this many seconds, after a keyframe's BA, freed heap goes back to the kernel
    (``lifecycle.release_free_memory``); 0: never. The allocator keeps freed heap for the BA's speed, and over a
    long stream that heap fragments: without it ba grew +41 % from 1,000 to 10,000 frames (docs/BENCHMARKS.md)."""

    def tracker(self) -> "Tracker":
        """The frame-rate tracker with these settings."""
        return self.tracker_factory()()

    def tracking_core(self) -> "LocalTracker | TrackerProcess":
        """The tracker as the tracking thread drives it: in a child process (``tracking_process``) or in-thread."""
        from services.ba.tracking_process import LocalTracker, TrackerProcess
        if self.tracking_process:
            return TrackerProcess(self.tracker_factory(), self.tracking_nice, name=f"kmvipe-tracking-{self.stream}")
        return LocalTracker(self.tracker_factory())

    def tracker_factory(self) -> "Callable[[], Tracker]":
        """A picklable factory of the tracker (a child process builds its own)."""
        from services.ba.frontend.tracker import Tracker
        params = self.frontend_params()
        return functools.partial(Tracker, params.motion, self.tracking_flow_params(), self.tracking_promote_after,
                                 params.relocalise)

    def tracking_flow_params(self) -> FlowParams:
        """Flow parameters of the tracker: cheaper than the window's (it runs on every frame)."""
        return dataclasses.replace(self.flow_params(), preset=self.tracking_flow_preset,
                                   finest_scale=self.tracking_finest_scale)

    def frontend_params(self) -> FrontendParams:
        """The frozen parameters of :class:`services.ba.frontend.frontend.Frontend`."""
        graph = GraphParams(window=self.window, temporal_radius=self.temporal_radius,
                            proximity_max_flow=self.proximity_max_flow, proximity_max_edges=self.proximity_max_edges,
                            proximity_overlap=self.proximity_overlap, loop_max_edges=self.loop_max_edges,
                            loop_every=self.loop_every, remove_max_flow=self.remove_max_flow,
                            global_radius=self.global_radius, landmark_overlap=self.landmark_overlap)
        return FrontendParams(
            graph=graph, init=InitParams(min_keyframes=self.init_keyframes, min_flow=self.init_min_flow,
                                         max_keyframes=self.init_max_keyframes),
            motion=MotionParams(huber=self.motion_huber, max_speed_growth=self.tracking_max_speed_growth),
            ba=self.ba_params(), weak_keyframe_gap=self.weak_keyframe_gap,
            burst_gap=self.burst_gap,
            global_ba=self.ba_params(global_ba=True), flow=self.flow_params(), focal_after=self.focal_after,
            focal_until=self.focal_until, ark_with_focal=self.ark_with_focal,
            window_ark_per_edge=self.window_ark_per_edge, keep_keyframes=self.keep_keyframes,
            landmark_keyframes=self.landmark_keyframes,
            live_flow_downscale=self.live_flow_downscale, live_iterations=self.live_iterations,
            keyframe_flow_downscale=self.keyframe_flow_downscale,
            full_size_below_parallax=self.full_size_below_parallax,
            live_max_deferred=self.live_max_deferred, final_align_s=self.final_align_s,
            live_window=self.live_window, live_flow_preset=self.live_flow_preset,
            live_calibration=self.live_calibration, background_ba_every=self.background_ba_every,
            background_ba_keyframes=self.background_ba_keyframes, background_ba_edges=self.background_ba_edges,
            background_ba_s=self.background_ba_s, settled_global_ba_s=self.settled_global_ba_s,
            live_background_ba_s=self.live_background_ba_s,
            settle_all_keyframes=self.settle_all_keyframes,
            global_ba_s=self.global_ba_s, relocalise=self.relocalise_params())

    def relocalise_params(self) -> RelocaliseParams:
        return RelocaliseParams(below_share=self.relocalise_below_share,
                                track_below_share=self.tracking_relocalise_below_share)
