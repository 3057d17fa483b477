"""Poses of non-keyframes: motion-only alignment to the two keyframes that bracket each frame in time.

A frame keeps its pose relative to the keyframe before it (its anchor), so a BA that moves the anchor moves
the frame with it; at end of stream every frame is aligned again against the final keyframes.

A frame tracking posed comes with tracking's flow from its reference keyframe. Its pose was solved against that
keyframe's depth and pose as they were then (on a live stream mapping is behind: often a depth carried over,
before any BA), and that, not the flow, is most of its error: solving it again with the same flow against the
keyframe as mapping refined it (:meth:`FramePoses.resolve`, no flow computed) takes the synthetic world's
tracked frames from 17 to 6 mm, at ~10 ms a frame instead of ~100 ms for two flows of mapping's own.
"""
from __future__ import annotations

import logging
import time
from bisect import bisect_left
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
import torch

from services.ba.core import flow as core_flow
from services.ba.core import se3, se3_numpy
from services.ba.core.host_arrays import as_numpy
from services.ba.frontend import motion
from services.ba.frontend.graph import STILL_STEP, KeyframeGraph, Targets
from services.ba.frontend.params import MotionParams
from services.common.own_pages import own_pages

logger = logging.getLogger(__name__)


@dataclass
class FrameRecord:
    """One non-keyframe."""

    seq: int
    stamp: int  # t_ns
    image: np.ndarray  # (h', w') uint8 grey, any size with the working aspect ratio
    anchor: int | None = None  # seq of the keyframe its relative pose refers to
    anchor_from_cam: torch.Tensor | None = None  # (4, 4) float64
    targets: dict[int, Targets] = field(default_factory=dict)  # keyframe seq -> targets into this frame
    interpolate_only: bool = False  # posed between its keyframes by time alone, no flow (live, mapping behind)
    focal: float = 0.0  # the map's grid focal when it was aligned (0: not aligned)
    measured: bool = False  # aligned with flow to its bracketing keyframes (not only where tracking put it)
    tracked_ref: int | None = None  # the keyframe tracking's flow into it starts from (in ``targets`` while held)
    resolved: bool = False  # solved again with tracking's flow against that keyframe as mapping refined it
    blind: bool = False  # its flow to the keyframes held no evidence (a covered lens, a blank view, a cut): posed
    # by time between its neighbours, and reported as a lost view
    strayed: bool = False  # its solved pose lay farther off the poses around it than the camera can have moved
    # (FramePoses._strayed): posed by time between its neighbours instead


def _around(seqs: list[int], seq: int) -> tuple[int | None, int | None]:
    """The nearest of the ascending ``seqs`` before and after ``seq`` (None where there is none)."""
    i = bisect_left(seqs, seq)
    after = i + (i < len(seqs) and seqs[i] == seq)
    return (seqs[i - 1] if i > 0 else None), (seqs[after] if after < len(seqs) else None)


def merge_ranges(ranges: list[tuple[int, int]]) -> list[tuple[int, int]]:
    """Inclusive integer ranges merged where they overlap or touch, ascending."""
    merged: list[tuple[int, int]] = []
    for first, last in sorted(ranges):
        if merged and first <= merged[-1][1] + 1:
            merged[-1] = (merged[-1][0], max(merged[-1][1], last))
        else:
            merged.append((first, last))
    return merged


def interpolate(pose_a: torch.Tensor, pose_b: torch.Tensor, frac: float) -> torch.Tensor:
    """Pose ``(4, 4)`` a fraction ``frac`` of the way from ``pose_a`` to ``pose_b`` (geodesic in SE3), as
    ``pose_a``'s tensor. On the host: torch's small operations on one 4x4 took 0.7 ms an interpolation, a quarter
    of the end of stream's frame solves (docs/BENCHMARKS.md); numpy's take 0.06 ms."""
    a = as_numpy(pose_a)
    rel = se3_numpy.inverse(a) @ as_numpy(pose_b)
    return torch.from_numpy(a @ se3_numpy.exp(frac * se3_numpy.log(rel))).to(pose_a)


def _at_time(ends: tuple[tuple[int, torch.Tensor], ...], stamp: int) -> torch.Tensor:
    """The pose at ``stamp`` between two (stamp, world_from_cam) ``ends``, interpolated by time."""
    (t0, p0), (t1, p1) = ends
    return interpolate(p0, p1, (stamp - t0) / max(t1 - t0, 1))


class FramePoses:
    """Non-keyframe records and their alignment against a :class:`KeyframeGraph`."""

    def __init__(self, params: MotionParams):
        self.params = params
        self.frames: dict[int, FrameRecord] = {}
        self._lost_before: list[tuple[int, int]] = []  # lost views among the frames dropped (lost_views)
        self._strayed_before = 0  # strayed frames among those dropped (strayed)

    def add(self, record: FrameRecord) -> None:
        self.frames[record.seq] = record

    def bracket(self, graph: KeyframeGraph, seq: int) -> tuple[int | None, int | None]:
        """Positions of the last keyframe before ``seq`` and the first after it (None where none)."""
        before = [k for k, s in enumerate(graph.seqs) if s < seq]
        after = [k for k, s in enumerate(graph.seqs) if s > seq]
        return (before[-1] if before else None), (after[0] if after else None)

    def pending(self, graph: KeyframeGraph) -> list[int]:
        """Seqs of frames not aligned yet whose later keyframe exists."""
        last = graph.seqs[-1] if len(graph) else -1
        return [s for s, f in self.frames.items() if f.anchor is None and s < last]

    def _targets(self, graph: KeyframeGraph, k: int, frame: FrameRecord) -> Targets:
        seq = graph.seqs[k]
        if seq not in frame.targets:
            work, scale = graph.images[k], self.params.flow_downscale
            size = (work.shape[1] // scale, work.shape[0] // scale)
            # at 1/scale, a grid cell is grid/scale pixels and the grid coordinates come out the same
            # ((x + 0.5)/grid - 0.5 with x the landing point at that resolution); fb_sigma is in its pixels
            # the preset's patches, not the dense ones of bare keyframe pairs (FlowParams.low_texture_patch_stride):
            # a person filling the view is as bare, dense patches follow it, and one frame's solve has nothing to
            # outvote it (the 10,000-frame orbit's frames 4150-4449: 0.048 m with them, 0.022 m without)
            params = replace(graph.flow_params, grid=graph.flow_params.grid // scale,
                             fb_sigma=graph.flow_params.fb_sigma / scale)
            keyframe = work if scale == 1 else cv2.resize(work, size, interpolation=cv2.INTER_AREA)
            image = frame.image if frame.image.shape[:2] == size[::-1] else cv2.resize(
                frame.image, size, interpolation=cv2.INTER_AREA if frame.image.shape[1] > size[0] else cv2.INTER_LINEAR)
            ft = core_flow.flow_targets(keyframe, image, params)
            # as tracking's: forward-backward consistency alone trusts DIS's smooth flow over a blank view
            confidence = ft.confidence * core_flow.photometric_agreement(keyframe, image, ft.target, params.grid)
            frame.targets[seq] = Targets(torch.from_numpy(own_pages(ft.target)),
                                         torch.from_numpy(own_pages(confidence)))
        return frame.targets[seq]

    def align(self, graph: KeyframeGraph, seq: int) -> torch.Tensor:
        """Align frame ``seq`` to its bracketing keyframes; store and return its world_from_cam ``(4, 4)``."""
        frame = self.frames[seq]
        a, b = self.bracket(graph, seq)
        kfs = [k for k in (a, b) if k is not None]
        if not kfs:
            raise ValueError(f"frame {seq}: no keyframe to align to")
        if a is not None and b is not None:
            span = max(graph.stamps[b] - graph.stamps[a], 1)
            init = interpolate(graph.poses[a], graph.poses[b], (frame.stamp - graph.stamps[a]) / span)
        else:
            init = graph.poses[kfs[0]]
        if frame.interpolate_only:
            between = self._between_neighbours(graph, frame)
            return self._anchor(graph, frame, kfs[0], init if between is None else between)
        tg = [self._targets(graph, k, frame) for k in kfs]
        dev = graph.device
        res = motion.align(init, torch.stack([graph.poses[k] for k in kfs]),
                           torch.stack([graph.disparity[k] for k in kfs]),
                           torch.stack([t.target for t in tg]).to(dev), torch.stack([t.confidence for t in tg]).to(dev),
                           graph.intrinsics, self.params)
        frame.measured = True
        frame.blind = not res.ok
        if frame.blind:
            logger.info("frame posed by time: its flow to the keyframes holds no evidence", extra={"seq": seq})
        pose = torch.from_numpy(res.pose).to(init)
        # the poses around it, looked up once: what its solve is checked against, and where it goes if refused
        ends = self._neighbours(graph, frame) if frame.blind or len(kfs) == 2 else None
        between = init if ends is None else _at_time(ends, frame.stamp)
        frame.strayed = not frame.blind and len(kfs) == 2 and self._strayed(graph, a, b, frame, pose, ends, between)
        if frame.strayed:
            logger.info("frame posed by time: its solved pose strayed off the path of the poses around it",
                        extra={"seq": seq})
        return self._anchor(graph, frame, kfs[0], between if frame.blind or frame.strayed else pose)

    def _strayed(self, graph: KeyframeGraph, a: int, b: int, frame: FrameRecord, pose: torch.Tensor,
                 ends: tuple[tuple[int, torch.Tensor], ...], expected: torch.Tensor) -> bool:
        """Whether ``pose``, solved for ``frame`` between keyframes ``a`` and ``b``, lies farther from
        ``expected``, where the poses around it (``ends``, :meth:`_neighbours`) put it by time, than the camera can
        have gone: ``max_speed_growth`` x their speed (or the keyframes', where that is higher) over the time to the
        nearer of them, as tracking bounds its poses and the window BA its keyframe steps. Weak flow that something
        moving dominates (the 10,000-frame orbit's person filling the view) solves for that thing's motion: frames
        1.5-2.2 m off a path whose keyframes held within 2 cm. A hand's curved path lies off the keyframes' chord by
        8 % of the scene's depth (the desk, 20 frames between keyframes) but not off its neighbours'. An offset under
        a hundredth of the scene's depth is never refused (it moves no pixel by more than about a grid px)."""
        (t0, p0), (t1, p1) = ends
        keyframe_speed = float((graph.poses[b][:3, 3] - graph.poses[a][:3, 3]).norm()) / max(
            graph.stamps[b] - graph.stamps[a], 1)
        speed = max(keyframe_speed, float((p1[:3, 3] - p0[:3, 3]).norm()) / max(t1 - t0, 1))
        nearer = max(min(frame.stamp - t0, t1 - frame.stamp), 0)
        depth = 1.0 / float(graph.disparity[a].median().clamp_min(1e-12))
        allowed = max(self.params.max_speed_growth * speed * nearer, STILL_STEP * depth)
        return float((pose[:3, 3] - expected[:3, 3]).norm()) > allowed

    def resolve(self, graph: KeyframeGraph, seq: int) -> torch.Tensor | None:
        """Solve tracked frame ``seq`` again with tracking's flow against its reference keyframe as the graph holds
        it now, from its current pose; no flow is computed. Stores and returns its world_from_cam; None when its
        reference keyframe is not held or the solve is refused (the pose stands)."""
        frame = self.frames[seq]
        ref = frame.tracked_ref
        current = self.pose(graph, seq)
        if ref is None or ref not in frame.targets or ref not in graph.seqs or current is None:
            return None
        k, t, dev = graph.index(ref), frame.targets[ref], graph.device
        res = motion.align(current, graph.poses[k][None], graph.disparity[k][None], t.target[None].to(dev),
                           t.confidence[None].to(dev), graph.intrinsics, self.params)
        frame.resolved = True
        if not res.ok or not bool(np.isfinite(res.pose).all()):
            return None
        return self._anchor(graph, frame, graph.index(frame.anchor), torch.from_numpy(res.pose).to(current))

    def resolvable(self, before: int | None = None, again: bool = False) -> list[int]:
        """Tracked frames :meth:`resolve` can improve, oldest first: not aligned with mapping's flow, tracking's
        flow held, its reference before keyframe seq ``before`` (None: any); with ``again`` also those already
        solved again (the keyframes changed since)."""
        return sorted(s for s, f in self.frames.items()
                      if f.anchor is not None and not f.measured and f.tracked_ref in f.targets
                      and (again or not f.resolved) and (before is None or f.tracked_ref < before))

    def _flowed(self, graph: KeyframeGraph) -> list[int]:
        """Seqs whose pose flow gave, ascending: the keyframes held and the frames tracked or aligned to them."""
        held = set(graph.seqs)
        return sorted(held | {s for s, f in self.frames.items()
                              if not (f.interpolate_only or f.blind or f.strayed) and f.anchor in held})

    def _neighbours(self, graph: KeyframeGraph, frame: FrameRecord,
                    flowed: list[int] | None = None) -> tuple[tuple[int, torch.Tensor], ...] | None:
        """(stamp, world_from_cam) of the nearest poses flow gave on either side of ``frame`` (``flowed``, from
        :meth:`_flowed`): keyframes, and frames tracked or aligned. None when one side has none."""
        before, after = _around(self._flowed(graph) if flowed is None else flowed, frame.seq)
        if before is None or after is None:
            return None
        return tuple((graph.stamps[graph.index(s)], graph.poses[graph.index(s)]) if s in graph.seqs
                     else (self.frames[s].stamp, self.pose(graph, s)) for s in (before, after))

    def _between_neighbours(self, graph: KeyframeGraph, frame: FrameRecord,
                            flowed: list[int] | None = None) -> torch.Tensor | None:
        """A frame no flow posed (tracking had no time for it), interpolated by time between the nearest poses on
        either side that flow did give (:meth:`_neighbours`). On a live stream tracking skips frames, often every
        other one, so those are a frame period apart where the keyframes are ~25 (the synthetic orbit at 30 Hz:
        50-80 mm off between keyframes). None when one side has no such pose."""
        ends = self._neighbours(graph, frame, flowed)
        return None if ends is None else _at_time(ends, frame.stamp)

    def interpolate_again(self, graph: KeyframeGraph) -> list[int]:
        """Every frame posed by time, interpolated again between its neighbours as they are now (after they were
        solved again or measured); no flow, ~1 ms a frame. Returns their seqs."""
        flowed = self._flowed(graph)
        done = []
        for seq in self.interpolated():
            frame = self.frames[seq]
            pose = self._between_neighbours(graph, frame, flowed)
            a = self.bracket(graph, seq)[0]
            if pose is not None and a is not None:
                self._anchor(graph, frame, a, pose)
                done.append(seq)
        return done

    def flow_spans(self, graph: KeyframeGraph, seqs: list[int]) -> dict[int, int]:
        """For each frame in ``seqs``, how many frames its pose's evidence spans: from tracking's reference keyframe
        for a tracked frame (DIS over a longer way, fewer cells left: 30 frames from its reference a synthetic frame
        keeps 3 % of them), between the flow-posed frames or keyframes around it for one posed by time."""
        flowed = self._flowed(graph)
        spans = {}
        for seq in seqs:
            frame = self.frames[seq]
            if not frame.interpolate_only:
                spans[seq] = seq - frame.tracked_ref if frame.tracked_ref is not None else 0
                continue
            before, after = _around(flowed, seq)
            spans[seq] = (seq if after is None else after) - (seq if before is None else before)
        return spans

    def align_at_end(self, graph: KeyframeGraph, deadline: float, realign_focal_change: float) -> None:
        """End of stream: frames still held aligned to their final keyframes until ``deadline``
        (time.monotonic()). First every tracked frame solved again with tracking's flow (:meth:`resolve`, ~10 ms
        each); then, with mapping's flow, those no flow of mapping's measured yet, the longest evidence first
        (:meth:`flow_spans`: the synthetic orbit's tracked frames are 40-90 mm off 20-35 frames from their
        reference, within ~2 mm of mapping's flow close to it), and those measured while the focal was still
        settling, more than ``realign_focal_change`` off the final one (their flow is kept: only the solve runs
        again; a 40 deg lens whose calibration started 18 % short: 2.5 -> 1.2 % of path, docs/BENCHMARKS.md),
        then every other measured frame the same way (BAs since its alignment may have moved its keyframes apart:
        the 40 deg lens, three frames aligned beside a keyframe turned back into a frame, 7.3 -> 0.4 % of path).
        Last, whatever the time, the frames tracking skipped are interpolated again between their neighbours as
        those now are (no flow)."""
        unmeasured = self.unmeasured()
        spans = self.flow_spans(graph, unmeasured)
        steps = [("resolve", s) for s in self.resolvable(again=True)]
        steps += [("measure", s) for s in sorted(unmeasured, key=lambda s: (-spans[s], s))]
        stale = self.stale_focal(float(graph.intrinsics[0]), realign_focal_change)
        steps += [("measure", s) for s in stale]
        steps += [("measure", s) for s in sorted(set(self.measured()) - set(stale))]
        for done, (step, seq) in enumerate(steps):
            if time.monotonic() >= deadline:
                logger.info("end of stream: frames left with their earlier poses (time bound)",
                            extra={"aligned": done, "left": len(steps) - done})
                break
            if step == "resolve":
                self.resolve(graph, seq)
            else:
                self.measure(graph, seq)
        self.interpolate_again(graph)

    def interpolated(self) -> list[int]:
        """Frames posed by time alone (no flow of tracking's or mapping's, none that held evidence, or a solve that
        strayed), oldest first."""
        return sorted(s for s, f in self.frames.items()
                      if (f.interpolate_only or f.blind or f.strayed) and f.anchor is not None)

    def lost_views(self) -> list[tuple[int, int]]:
        """(first, last) seqs of each run of frames whose view held no evidence, ascending: those dropped from
        memory already (kept as ranges, so a camera covered for hours costs a few numbers) and those held."""
        held = sorted(s for s, f in self.frames.items() if f.blind)
        return merge_ranges(self._lost_before + [(s, s) for s in held])

    def strayed(self) -> int:
        """How many frames of the stream are posed by time because their solve strayed (:meth:`_strayed`)."""
        return self._strayed_before + sum(f.strayed for f in self.frames.values())

    @staticmethod
    def _anchor(graph: KeyframeGraph, frame: FrameRecord, anchor: int, pose: torch.Tensor) -> torch.Tensor:
        frame.anchor = graph.seqs[anchor]
        frame.anchor_from_cam = se3.inverse(graph.poses[anchor]) @ pose
        frame.focal = float(graph.intrinsics[0])
        return pose

    def pose(self, graph: KeyframeGraph, seq: int) -> torch.Tensor | None:
        """Current world_from_cam of an aligned frame (its anchor's pose times its relative pose)."""
        frame = self.frames[seq]
        if frame.anchor is None or frame.anchor not in graph.seqs:
            return None
        return graph.poses[graph.index(frame.anchor)] @ frame.anchor_from_cam

    def unmeasured(self) -> list[int]:
        """Frames posed without flow of mapping's own (a live stream's: anchored where tracking put them, or
        interpolated by time), oldest first."""
        return sorted(s for s, f in self.frames.items() if f.anchor is not None and not f.measured)

    def measure(self, graph: KeyframeGraph, seq: int) -> torch.Tensor:
        """Align frame ``seq`` to its bracketing keyframes with mapping's flow, whatever posed it before."""
        self.frames[seq].interpolate_only = False
        return self.align(graph, seq)

    def stale_focal(self, focal: float, tolerance: float) -> list[int]:
        """Frames aligned with mapping's flow under a focal more than ``tolerance`` (relative) off ``focal``,
        oldest first: their relative pose was solved on another camera model."""
        return sorted(s for s, f in self.frames.items()
                      if f.measured and f.focal > 0 and abs(f.focal / focal - 1.0) > tolerance)

    def measured(self) -> list[int]:
        """Frames aligned with mapping's flow, oldest first."""
        return sorted(s for s, f in self.frames.items() if f.measured and f.anchor is not None)

    def anchored_to(self, anchors: set[int]) -> list[int]:
        return [s for s, f in self.frames.items() if f.anchor in anchors]

    def drop_before(self, kf_seq: int) -> int:
        """Forget every frame older than keyframe ``kf_seq`` (their keyframes left the graph; the poses last
        published for them are final). Returns how many were dropped."""
        old = [s for s in self.frames if s < kf_seq]
        self._lost_before = merge_ranges(self._lost_before + [(s, s) for s in old if self.frames[s].blind])
        self._strayed_before += sum(self.frames[s].strayed for s in old)
        for s in old:
            del self.frames[s]
        return len(old)

    def unanchor(self) -> None:
        """The map started again (new scale and focal): every frame is aligned afresh (its flows are kept)."""
        for f in self.frames.values():
            f.anchor = f.anchor_from_cam = None

    def forget_targets(self, kf_seq: int) -> None:
        """A keyframe left the graph: targets from it are stale, and frames anchored to it are re-aligned."""
        for f in self.frames.values():
            f.targets.pop(kf_seq, None)
            if f.anchor == kf_seq:
                f.anchor = f.anchor_from_cam = None
