"""Frame-rate tracking: every frame's pose at once, motion-only against the newest mapped keyframe.

Mapping (window BA) runs per keyframe and takes hundreds of milliseconds; a frame cannot wait for it. The
tracker holds a snapshot of one reference keyframe — its pose, grid disparity and image, as the last BA left
them — and aligns each frame to it: DIS flow from the reference into the frame (at the size frames arrive in),
started from the flow a constant-velocity prediction induces, then the 6-dof Gauss-Newton of
:mod:`services.ba.frontend.motion`. Mapping later revises the pose against the keyframes that bracket the
frame (:mod:`services.ba.frontend.frames`). As in DSO's coarse tracker, the reference only changes when the
mapper hands over a newer keyframe, so tracking never reads state that mapping is changing.

When mapping falls behind (a live camera on a shared CPU), waiting for its next keyframe would leave tracking
aligned to a keyframe ever further back until the flow breaks. So while mapping does not hold the keyframe
before the newest, a keyframe that tracking itself aligned is promoted to reference, its depth the reference's
grid disparity carried over by the tracked motion (:func:`propagate_disparity`, as SVO and LSD-SLAM carry depth
to a new keyframe); mapping's result replaces it once mapping is at most one keyframe behind.

numpy and OpenCV only: the tracker runs in a process of its own (services/ba/tracking_process.py), which would
hold ~200 MB more for importing torch. References from mapping's graph are read on the host
(:meth:`Tracker.set_reference`).
"""
from __future__ import annotations

from dataclasses import replace
from typing import NamedTuple

import cv2
import numpy as np

from services.ba.core import flow as core_flow
from services.ba.core import se3_numpy as se3
from services.ba.core.host_arrays import as_numpy
from services.ba.core.params import GRID, FlowParams
from services.ba.core.projective_numpy import induced_flow_field
from services.ba.frontend import motion, pnp
from services.ba.frontend.carried_depth import depth_scale, propagate_disparity, similarity_about
from services.ba.frontend.params import MotionParams, RelocaliseParams
from services.ba.frontend.rotation import bearing_rotation


class Reference(NamedTuple):
    """A mapped keyframe the tracker aligns frames to (a snapshot: the mapper never changes it in place)."""

    seq: int
    stamp: int  # t_ns
    pose: np.ndarray  # (4, 4) float64 world_from_cam
    disparity: np.ndarray  # (h, w) float64 grid disparity
    intrinsics: np.ndarray  # (4,) float64 grid intrinsics
    image: np.ndarray  # (H, W) uint8 grey at working resolution
    previous: tuple[int, np.ndarray] | None = None  # (t_ns, world_from_cam) of the keyframe before: its motion
    known: np.ndarray | None = None  # (h, w) 1 where the disparity is measured, 0 where it was only filled in
    speed: float | None = None  # mapping's keyframe speed (length per ns, steps.reference_speed); None: not yet known

    def on_host(self) -> "Reference":
        """The same reference with numpy float64 arrays (mapping builds it from its graph's tensors)."""
        optional = lambda a: None if a is None else as_numpy(a)  # noqa: E731
        previous = None if self.previous is None else (self.previous[0], as_numpy(self.previous[1]))
        return self._replace(pose=as_numpy(self.pose), disparity=as_numpy(self.disparity),
                             intrinsics=as_numpy(self.intrinsics), previous=previous, known=optional(self.known))


class Tracked(NamedTuple):
    seq: int
    stamp: int
    pose: np.ndarray  # (4, 4) float64 world_from_cam
    ref_seq: int  # the keyframe it was aligned to
    ok: bool  # False: too little flow to align; the pose is the constant-velocity prediction
    target: np.ndarray | None = None  # (h, w, 2) float32: where the reference's grid cells landed (grid coords)
    confidence: np.ndarray | None = None  # (h, w) float32: their confidence (flow and photometric agreement)
    refused: bool = False  # its flow or PnP pose lay beyond mapping's speed (Tracker._plausible): the prediction


MAX_PROMOTED = 64  # keyframe poses tracking remembers, to correct its carried-over reference by mapping's
MAX_EXTRAPOLATION = 8.0  # a prediction extends a motion at most this many times its own duration


def _extrapolate(t0: int, pose0: np.ndarray, t1: int, pose1: np.ndarray, stamp: int) -> np.ndarray:
    """The motion from (t0, pose0) to (t1, pose1) continued at the same rate to ``stamp`` (geodesic in SE3)."""
    span = t1 - t0
    frac = (stamp - t1) / span if span > 0 else 0.0
    rel = se3.inverse(pose0) @ pose1
    return se3.orthonormalize(pose1 @ se3.exp(min(frac, MAX_EXTRAPOLATION) * se3.log(rel)))


# A tracked pose is trusted (anchors the frame, promotes a keyframe) only with this much evidence: at least this
# share of the reference's grid cells left after the robust weights, and a weighted RMS flow residual below this
# (grid px). On the synthetic world a frame 14 frames from its reference still has 4 % and 0.57 px; 30 frames away
# 3 % and 1.2 px, a pose one should not build on.
TRACK_MIN_SHARE = 0.03
TRACK_MAX_RMS = 1.0
def _holds(res: motion.MotionResult, cells: int) -> bool:
    """Tracking's checks of an alignment: solved, finite, on enough of the grid and with a small enough residual."""
    return (res.ok and res.weight >= TRACK_MIN_SHARE * cells and res.rms <= TRACK_MAX_RMS
            and bool(np.isfinite(res.pose).all()))


class Tracker:
    """Aligns frames in arrival order; feed references with :meth:`set_reference` as mapping produces them."""

    def __init__(self, params: MotionParams, flow: FlowParams, promote_after: int = 1,
                 relocalise_params: RelocaliseParams = RelocaliseParams()):
        self.params = params
        self.relocalise = relocalise_params
        self.relocalised = 0  # frames whose pose came from a PnP start or PnP alone (_relocalise)
        self._ref_features: tuple[Reference, pnp.Features] | None = None  # the reference's ORB features
        # A frame was not tracked (a lost view, a whip pan) and no frame since was held by its flow alone (more
        # than track_below_share of the grid): the constant-velocity prediction is a guess, and flow started from
        # it can settle on a wrong pose that still passes the checks (the synthetic orbit after a 20-frame blank:
        # 0.2-0.9 m off for 7 frames). Each frame then also starts from a PnP pose against the reference
        # (_relocalise). Only then: PnP on every weakly held frame cost the 30 Hz synthetic stream its frame rate
        # (p99 124 -> 845 ms, 49 frames dropped by tracking's backlog).
        self.lost = False
        self.promote_after = promote_after  # mapping's reference is kept while it is at most this many keyframes
        # behind the newest tracking has seen; further behind, tracking promotes its own keyframes
        scale = params.flow_downscale
        # at 1/scale a grid cell is grid/scale pixels and grid coordinates come out the same (frames.py)
        self.flow = replace(flow, grid=flow.grid // scale, fb_sigma=flow.fb_sigma / scale)
        self.reference: Reference | None = None  # what frames are aligned to: mapping's, or a carried-over one
        self._mapped: Reference | None = None  # mapping's newest
        self._head: Reference | None = None  # a keyframe promoted by tracking while mapping is behind
        self._keyframes: list[int] = []  # seqs of the last keyframes tracking saw (promote_after + 1)
        self._ref_small: np.ndarray | None = None
        self._history: list[Tracked] = []  # the last two tracked frames (constant-velocity prediction)
        self._promoted: dict[int, np.ndarray] = {}  # keyframe seq -> world_from_cam tracking gave it
        self._carried: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # promoted seq -> its carried (disparity, known)
        self._origin: tuple[np.ndarray, np.ndarray] | None = None  # first frame before the map: small grey, K
        self._origin_flow: np.ndarray | None = None  # the last flow from it (DIS's start for the next frame)

    def set_reference(self, ref: Reference) -> None:
        """Mapping's newest keyframe. Tracking uses it unless it holds a carried-over reference and ``ref`` is
        older than the keyframe before the newest one tracking has seen (mapping is that far behind); then the
        carried-over reference is corrected by what mapping found for ``ref`` (:meth:`_correct`)."""
        ref = ref.on_host()
        self._mapped = ref
        behind = self._head is not None and ref.seq < self._head.seq
        if not behind:
            self._head = None
            self._use(ref)
        else:
            self._correct(ref)

    def _correct(self, ref: Reference) -> None:
        """Mapping refined keyframe ``ref`` that tracking had posed and carried depth past: the drift tracking
        accumulated up to it is the difference of the two poses, and, where tracking had carried depth to ``ref``
        itself, of the two depths' scales. The carried-over reference, the motion history and the later promoted
        keyframes move by that similarity about ``ref`` (:func:`similarity_about`), and the reference takes its depth
        afresh from ``ref``'s map where that covers as much of it (DSO's coarse tracker likewise always tracks
        against the newest mapped depth). Without it tracking stays a visual odometry for as long as mapping is
        behind (KITTI 07 live: 7 m)."""
        tracked = self._promoted.get(ref.seq)
        if tracked is None:
            return
        scale = self._depth_scale(ref)
        fix = similarity_about(ref.pose, tracked, scale)
        head = self._head
        pose = fix(head.pose)
        previous = None if head.previous is None else (head.previous[0], fix(head.previous[1]))
        disparity, known = head.disparity / scale, head.known
        fresh, fresh_known = propagate_disparity(ref.pose, pose, ref.disparity, ref.intrinsics)
        if known is None or float(fresh_known.mean()) >= 0.8 * float(np.mean(known)):
            disparity, known = fresh, fresh_known
        self._head = head._replace(pose=pose, disparity=disparity, known=known, previous=previous,
                                   intrinsics=ref.intrinsics)
        self._history = [t._replace(pose=fix(t.pose)) for t in self._history]
        self._promoted = {seq: (p if seq < ref.seq else fix(p)) for seq, p in self._promoted.items()}
        self._promoted[ref.seq] = ref.pose  # corrected now: the same reference again changes nothing
        # older ones are behind mapping for good: mapping's references only move forward
        self._carried = {seq: (d[0] / scale, d[1]) for seq, d in self._carried.items() if seq > ref.seq}
        self._use(self._head)

    def _depth_scale(self, ref: Reference) -> float:
        """Mapping's depth over the depth tracking carried to keyframe ``ref`` (1 where it carried none there)."""
        carried = self._carried.get(ref.seq)
        return 1.0 if carried is None else depth_scale(*carried, ref.disparity)

    def keyframe_seen(self, seq: int) -> None:
        """A keyframe went past tracking, posed or not: it counts towards how far behind mapping is."""
        if not self._keyframes or self._keyframes[-1] != seq:
            self._keyframes = (self._keyframes + [seq])[-(self.promote_after + 1):]

    def promote(self, seq: int, stamp: int, image: np.ndarray, pose) -> None:
        """Keyframe ``seq`` was tracked to ``pose`` (``image``: (H, W) grey, working resolution). When mapping
        does not yet hold the keyframe before it, it becomes the reference, with the current reference's depth
        carried over; otherwise mapping's reference stays (it is at most one keyframe back, and refined). Either
        way its pose and the depth tracking carried to it are kept, for mapping's correction (:meth:`_correct`)."""
        pose = as_numpy(pose)
        self.keyframe_seen(seq)
        ref = self.reference
        disparity, known = propagate_disparity(ref.pose, pose, ref.disparity, ref.intrinsics)
        self._promoted[seq], self._carried[seq] = pose, (disparity, known)
        for kept in (self._promoted, self._carried):
            if len(kept) > MAX_PROMOTED:
                kept.pop(min(kept))
        if self._mapped is not None and self._mapped.seq >= self._oldest_kept():
            return
        self._head = Reference(seq, stamp, pose, disparity, ref.intrinsics, image, (ref.stamp, ref.pose), known,
                               ref.speed)
        self._use(self._head)

    def _oldest_kept(self) -> int:
        """Seq of the oldest keyframe mapping's reference may be and still be tracked against."""
        if len(self._keyframes) <= self.promote_after:
            return -1
        return self._keyframes[0]

    def _use(self, ref: Reference) -> None:
        scale = self.params.flow_downscale
        h, w = ref.image.shape
        self._ref_small = ref.image if scale == 1 else cv2.resize(ref.image, (w // scale, h // scale),
                                                                  interpolation=cv2.INTER_AREA)
        self.reference = ref

    def _provisional(self, seq: int, stamp: int, image: np.ndarray, intrinsics: np.ndarray) -> Tracked:
        """Before the map: a monocular camera has no translation (nor scale) until there is parallax, but its
        rotation is observable. The stream's first frame defines the world (identity); a later one gets the
        rotation that best maps the first frame's bearings onto its own along DIS flow (Kabsch on bearings,
        outliers dropped), and no translation. Published as tracked, never anchored: mapping revises it once
        the map starts. It keeps a live consumer's first poses within the tracking latency from the first frame
        on (KITTI 07: the map starts 0.7 s after frame 0)."""
        grey = core_flow.to_grey(np.asarray(image))
        if self._origin is None:  # later frames are resized to its size (frames arrive at half the working size)
            self._origin = (grey, np.asarray(intrinsics, np.float64))
            self._origin_flow = None
            return Tracked(seq, stamp, np.eye(4), -1, False)
        small, k = self._origin
        size = (small.shape[1], small.shape[0])
        if grey.shape[:2] != small.shape:
            grey = cv2.resize(grey, size, interpolation=cv2.INTER_AREA if grey.shape[1] > size[0] else cv2.INTER_LINEAR)
        ft = core_flow.flow_targets(small, grey, self.flow, self._origin_flow)
        self._origin_flow = ft.flow
        pose = np.eye(4)
        pose[:3, :3] = bearing_rotation(ft.target, ft.confidence, k, self.flow.grid).T
        return Tracked(seq, stamp, pose, -1, False)

    def reset(self) -> None:
        """A new stream: forget the reference and the motion."""
        self.reference, self._ref_small, self._history = None, None, []
        self._origin = self._origin_flow = None
        self._mapped = self._head = None
        self._keyframes = []
        self._promoted, self._carried = {}, {}
        self.lost = False

    def predict(self, stamp: int) -> np.ndarray:
        """Constant-velocity world_from_cam at time ``stamp``: from the last two tracked frames while tracking
        holds, else from the motion between the reference and the keyframe before it (mapping's estimate)."""
        ref = self.reference
        hist = self._history
        if len(hist) == 2 and hist[0].ok and hist[1].ok and hist[1].stamp >= ref.stamp:
            return _extrapolate(hist[0].stamp, hist[0].pose, hist[1].stamp, hist[1].pose, stamp)
        if ref.previous is not None:
            return _extrapolate(*ref.previous, ref.stamp, ref.pose, stamp)
        return ref.pose

    def track(self, seq: int, stamp: int, image: np.ndarray, intrinsics: np.ndarray | None = None) -> Tracked | None:
        """Pose of frame ``seq`` (``image``: (h, w) grey or (h, w, 3), any size with the working aspect ratio).
        Before the first reference (the map has not started) a provisional rotation-only pose when ``intrinsics``
        ((4,) fx, fy, cx, cy of ``image``) are given (:meth:`_provisional`), else None."""
        ref = self.reference
        if ref is None:
            return None if intrinsics is None else self._provisional(seq, stamp, image, intrinsics)
        small = self._ref_small
        size = (small.shape[1], small.shape[0])
        grey = core_flow.to_grey(np.asarray(image))
        if grey.shape[:2] != small.shape:
            grey = cv2.resize(grey, size, interpolation=cv2.INTER_AREA if grey.shape[1] > size[0] else cv2.INTER_LINEAR)
        guess = self.predict(stamp)
        res, ft, measured = self._align(guess, grey)
        cells = ref.disparity.size
        below = self.relocalise.track_below_share
        if below > 0 and self.lost:
            out = self._relocalise(seq, stamp, grey, res, ft, measured)
            if out is not None and not self._plausible(out.pose, stamp):
                out = Tracked(seq, stamp, guess, ref.seq, False, refused=True)
            if out is not None:
                self._history = (self._history + [out])[-2:]
                # found again once the prediction's own flow holds a frame
                self.lost = out.target is None or res.weight < below * cells
                return out
        ok = _holds(res, cells)
        refused = ok and not self._plausible(res.pose, stamp)
        ok = ok and not refused
        pose = res.pose if ok else guess
        # the flow goes with the pose: mapping can solve the frame again against the reference's refined depth
        # without a flow of its own (frames.FramePoses.align)
        out = Tracked(seq, stamp, pose, ref.seq, ok, ft.target, measured, refused)
        self._history = (self._history + [out])[-2:]
        self.lost = below > 0 and (self.lost or not ok) and not (ok and res.weight >= below * cells)
        return out

    def _plausible(self, pose: np.ndarray, stamp: int) -> bool:
        """``pose`` lies within ``max_speed_growth`` x mapping's speed x the time from the reference of it. Flow
        that holds and PnP with enough inliers can still slide far along what a view barely constrains (a person
        filling it); kept, such a pose also becomes the next frame's prediction."""
        ref = self.reference
        if ref.speed is None or self.params.max_speed_growth <= 0:
            return True
        reach = self.params.max_speed_growth * ref.speed * max(abs(stamp - ref.stamp), 1)
        return float(np.linalg.norm(pose[:3, 3] - ref.pose[:3, 3])) <= reach

    def _relocalise(self, seq: int, stamp: int, grey: np.ndarray, res, ft, measured) -> Tracked | None:
        """The frame's pose from PnP against the reference (:mod:`relocalise`), when the flow aligned from the
        prediction (``res``) barely supports it. The alignment is run again from the PnP pose and the better
        supported of the two kept; if that fails tracking's checks, or keeps less than ``track_below_share`` of the
        grid and lands more than a grid pixel of induced flow away from the PnP pose, the flow is not trusted: the
        PnP pose is the frame's, with no flow for mapping to solve it again by (the synthetic orbit 31 frames after
        its reference, after a blank: PnP 0.7 deg off, its flow's alignment 6 deg). None: PnP found no pose."""
        ref = self.reference
        scale, cells = self.params.flow_downscale, ref.disparity.size
        if self._ref_features is None or self._ref_features[0] is not ref:
            self._ref_features = (ref, pnp.orb_features(ref.image, self.relocalise))
        # a carried-over reference's filled-in cells hold the median disparity, not a point: left out (0)
        disparity = ref.disparity if ref.known is None else ref.disparity * ref.known
        found = pnp.pose_from_features(self._ref_features[1], ref.pose, disparity, ref.intrinsics,
                                       pnp.orb_features(grey, self.relocalise, scale), self.relocalise)
        if found is None:
            return None
        again = self._align(found.pose, grey)
        from_pnp = again[0].ok and (not res.ok or again[0].weight > res.weight)
        if from_pnp:
            res, ft, measured = again
        trusted = _holds(res, cells)
        if trusted and res.weight < self.relocalise.track_below_share * cells:
            flows = [induced_flow_field(ref.pose, pose, ref.disparity, ref.intrinsics, GRID // scale)
                     for pose in (found.pose, res.pose)]
            trusted = float(np.linalg.norm(flows[0] - flows[1], axis=-1).mean()) * scale / GRID <= 1.0  # grid px
        if trusted:
            self.relocalised += int(from_pnp)
            return Tracked(seq, stamp, res.pose, ref.seq, True, ft.target, measured)
        self.relocalised += 1
        return Tracked(seq, stamp, found.pose, ref.seq, True)

    def _align(self, guess: np.ndarray, grey: np.ndarray):
        """Frame ``grey`` (at the reference's small size) aligned to the reference from ``guess``: DIS started
        from the flow ``guess`` induces. Returns (motion result, flow targets, their measured confidence)."""
        ref, small = self.reference, self._ref_small
        scale = self.params.flow_downscale
        init = induced_flow_field(ref.pose, guess, ref.disparity, ref.intrinsics, GRID // scale)
        ft = core_flow.flow_targets(small, grey, self.flow, init)
        measured = (ft.confidence * core_flow.photometric_agreement(small, grey, ft.target, self.flow.grid)
                    ).astype(np.float32)
        # a carried-over depth says nothing where no point landed; the flow there is still good against a mapped one
        confidence = measured if ref.known is None else measured * ref.known.astype(np.float32)
        res = motion.align(guess, ref.pose[None], ref.disparity[None], ft.target[None], confidence[None],
                           ref.intrinsics, self.params)
        return res, ft, measured
