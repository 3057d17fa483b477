"""The BA frontend: keyframes and frames in, graph state and every frame's pose out (no transport).

Per keyframe: before the map exists, keyframes are collected until the first and newest have parallax, then a
two-view start (essential matrix + triangulation) seeds poses and disparities and a BA refines them; keyframes
whose flow a rotation explains (a camera turning on the spot) start a map of rotations instead (start.py). After
that each new keyframe is aligned motion-only to the previous one, gets temporal and proximity edges, and a
few BA iterations run over the sliding window (the oldest window pose is the gauge). A redundant second-newest
keyframe is turned back into a frame. Frames are aligned motion-only to their two bracketing keyframes.

Memory is bounded by the window, not by the stream: once more than ``keep_keyframes`` keyframes are held, the
oldest leaves the graph with the frames before it (the poses last published for them are final; the mapstore
keeps their geometry). At end of stream a BA over the keyframes still held runs and their frames are aligned
again, so end-of-stream work does not grow with the stream either.
"""
from __future__ import annotations

import dataclasses
import logging

import numpy as np
import torch

from services.ba.core import flow as core_flow
from services.ba.core import se3
from services.ba.core.host_arrays import as_numpy
from services.ba.frontend import init, inputs, keyframe_pose, start, steps, upkeep
from services.ba.frontend.frames import FramePoses, FrameRecord
from services.ba.frontend.graph import KeyframeGraph, Targets, grid_intrinsics, own_pages_tensor, working_intrinsics
from services.ba.frontend.inputs import FrameInput, KeyframeInput
from services.ba.frontend.params import FrontendParams, focal_ba
from services.ba.frontend.refinement import Refinement
from services.ba.frontend.carried_depth import propagate_disparity
from services.ba.frontend.tracker import Reference
from services.ba.frontend.updates import Update, graph_update, pose_update
from services.common.own_pages import own_pages

logger = logging.getLogger(__name__)


class Frontend(Refinement):
    """Stateful frontend; see the module docstring. ``device``: where BA tensors live."""

    _supports: tuple[float, ...] = ()  # the grid shares the flows of the last keyframes kept supported (_lost_support);
    # a class default so that a ba checkpoint of an earlier version, which lacks it, restores
    _published: np.ndarray = np.zeros(4)  # the grid intrinsics the last update reported (_intrinsics_changed); a
    # class default for the same reason (never changed in place: each update assigns a new array)

    def __init__(self, params: FrontendParams = FrontendParams(), device: torch.device | str = "cpu"):
        self.params = params
        self.device = torch.device(device)
        self.graph: KeyframeGraph | None = None
        self.frames = FramePoses(params.motion)
        self.initialised = False
        self.metric = False
        self._size = (0, 0)
        self._calibrated = False  # the multi-start focal calibration ran (start.calibrate_focal)
        self._live = False  # the newest keyframe came from a real-time stream
        self.relocalised = 0  # keyframes aligned from a PnP start (relocalise.realign_keyframe)
        self._deferred = 0  # keyframes in a row whose window BA was left to a later keyframe
        self._since_global = 0  # keyframes joined since the last BA over every held keyframe (refine_globally)
        self._background_bas = 0  # BAs over every held keyframe during the stream (refine_globally)
        self._carried: dict[int, np.ndarray] = {}  # deferred keyframe seq -> (h, w) 1 where its carried-over
        # disparity is measured (a point landed), 0 where filled in; emptied by the next window BA

    # --- inputs ----------------------------------------------------------------------------------------
    def add_keyframe(self, kf: KeyframeInput) -> Update:
        grey = self._check(kf)
        g = self.graph
        prior = None if kf.disparity_prior is None else torch.from_numpy(np.asarray(kf.disparity_prior, np.float64))
        codes = None if kf.codes is None else torch.from_numpy(np.asarray(kf.codes, np.float32))
        pose, disp = self._predict(prior)
        if kf.pose_guess is not None and self.initialised and bool(torch.isfinite(kf.pose_guess).all()):
            pose = kf.pose_guess.to(self.device, torch.float64)
        k = g.append(kf.seq, kf.t_ns, grey, codes, prior, pose, disp, kf.native_codes)
        self._live = kf.realtime
        g.flow_downscale = self.params.live_flow_downscale if kf.realtime else self.params.keyframe_flow_downscale
        g.full_size_below_parallax = 0.0 if kf.realtime else self.params.full_size_below_parallax
        # the cheap preset only refines flow the map predicts; the two-view start has no prediction to begin from
        # (ultrafast alone failed it on 128x96 live flows)
        g.flow_preset = self.params.live_flow_preset if kf.realtime and self.initialised else None
        try:
            update = self._integrate(k, kf.defer_ba)
            self._since_global += 1
            return update
        except Exception:
            if k < len(g) and g.seqs[k] == kf.seq:  # leave the graph as it was before this keyframe
                g.remove(k)
            raise

    def _integrate(self, k: int, defer: bool = False) -> Update:
        g = self.graph
        if not self.initialised:
            return self._try_initialise()
        support, relocalised = keyframe_pose.align_keyframe(g, k, self._carried, self.params)
        self.relocalised += relocalised
        turned = ("keyframe its flow barely supports" if self._lost_support(k, support)
                  else "keyframe in a burst" if self._in_burst(k) else None)
        if turned:
            logger.info(f"{turned} turned into a frame",
                        extra={"seq": upkeep.to_frame(g, self.frames, k), "share": round(support, 3)})
            return Update()
        self._supports = (self._supports + (support,))[-6:]
        calibrating = not self._calibrated and len(g) >= self.params.focal_after and self.params.ba.optimise_focal
        if defer and not calibrating and self._deferred < self.params.live_max_deferred:
            return self._defer(k)
        self._deferred = 0
        if calibrating:
            self._calibrated = True
            start.calibrate_focal(g, self.frames, self.params, self._live)
        self._add_proximity(k)
        window = self._window()
        if g.run(window, g.pairs(window, self.params.graph.temporal_radius), self._ba_params(window),
                 codes_per_edge=self.params.window_ark_per_edge) is None:
            window = self._drop_unconstrained(window)
        updated = set(window)
        removed = self._remove_redundant()
        if removed is not None:
            updated = {g.index(s) for s in removed if s in g.seqs}
        update = self._update(sorted(updated))
        self._carried.clear()
        self._prefetch_global_edges()
        self._retire()
        return update

    def _prefetch_global_edges(self) -> None:
        """Flow targets of the end-of-stream BA's temporal edges beyond the window's radius, for the keyframe
        before the newest (the newest may still be turned back into a frame): computed now, one pair per keyframe,
        the end of stream only solves (KITTI 07: 8 s of flow at the end otherwise)."""
        g, gp = self.graph, self.params.graph
        k = len(g) - 2
        for back in range(gp.temporal_radius + 1, gp.global_radius + 1):
            if k - back >= 0:
                g.targets(k - back, k)

    def _defer(self, k: int) -> Update:
        """Keyframe ``k`` joins the graph where motion-only alignment put it, with its proximity candidates; its
        other edges' flows and the window BA come with a later keyframe (ORB-SLAM's local mapping likewise gives up
        local BA while keyframes queue). Its pose and its frames' go out; its geometry waits for that BA."""
        self._deferred += 1
        g = self.graph
        # its depth carried over from the newest keyframe a BA refined (not that keyframe's map as it is; one hop,
        # not along a chain of carried depths): the BA that comes starts there, and tracking takes it as its
        # reference at once
        src = keyframe_pose.newest_refined(g, self._carried, k)
        src = k - 1 if src is None else src
        disparity, known = propagate_disparity(g.poses[src], g.poses[k], g.disparity[src], g.intrinsics)
        g.disparity[k] = own_pages_tensor(torch.from_numpy(disparity).to(g.disparity[k - 1]))
        self._carried[g.seqs[k]] = known
        self._add_proximity(k)
        seqs = [self.graph.seqs[k]]
        for seq in self.frames.pending(self.graph):
            self.frames.align(self.graph, seq)
            seqs.append(seq)
        self._retire()
        return Update(poses=pose_update(self.graph, self.frames, sorted(set(seqs))))

    def _retire(self) -> None:
        """Drop the oldest keyframes beyond ``keep_keyframes`` with the frames before the new oldest one; of those
        that show a place no landmark shows, up to ``landmark_keyframes`` stay as landmarks."""
        g, p = self.graph, self.params
        recent = g.recent()
        while len(recent) > p.keep_keyframes:
            k = recent[0]
            if len(g.landmarks) < p.landmark_keyframes and upkeep.new_place(g, k, p.graph):
                g.landmarks.add(g.seqs[k])
                logger.info("keyframe kept as a landmark", extra={"seq": g.seqs[k], "landmarks": len(g.landmarks)})
            else:
                g.remove(k)
            recent = g.recent()
        self.frames.drop_before(g.seqs[recent[0]])

    def reference(self) -> Reference | None:
        """Snapshot of the newest keyframe for the tracker, in numpy (None before the map starts)."""
        g = self.graph
        if g is None or not self.initialised or len(g) == 0:
            return None
        k = len(g) - 1
        snap = lambda t: as_numpy(t).copy()  # noqa: E731 — a CPU tensor's numpy view would follow later BAs
        previous = (g.stamps[k - 1], snap(g.poses[k - 1])) if k > 0 else None
        known = self._carried.get(g.seqs[k])  # a deferred keyframe: its depth carried over, no BA yet
        speed = steps.reference_speed(g, k + 1) if k >= 2 and not steps.never_moved(g, k + 1) else None
        return Reference(g.seqs[k], g.stamps[k], snap(g.poses[k]), snap(g.disparity[k]), snap(g.intrinsics),
                         g.images[k], previous, None if known is None else known.copy(), speed)

    def add_frame(self, frame: FrameInput) -> Update:
        image = own_pages(core_flow.to_grey(np.asarray(frame.image)))
        if self.graph is not None and frame.seq in self.graph.seqs:
            raise ValueError(f"frame {frame.seq} is already a keyframe")
        record = FrameRecord(frame.seq, frame.t_ns, image, interpolate_only=frame.interpolate_only)
        if frame.tracked_flow is not None:  # kept to solve the frame again (frames.py)
            record.tracked_ref, target, confidence = frame.tracked_flow
            record.targets[record.tracked_ref] = Targets(own_pages_tensor(target), own_pages_tensor(confidence))
        if frame.tracked is not None and self.graph is not None and frame.tracked[0] in self.graph.seqs:
            # tracking already aligned it to a keyframe: anchored there, it moves with every BA of that keyframe
            # and needs no flow of its own (its pose went out when it was tracked)
            record.anchor, record.anchor_from_cam = frame.tracked[0], frame.tracked[1].to(self.device)
            self.frames.add(record)
            return Update()
        if frame.tracked_world is not None and self.initialised and self.graph.seqs[0] < frame.seq:
            # tracked against a keyframe mapping merged or has not mapped yet (a live camera, mapping behind):
            # anchored to the mapped keyframe before it where tracking put it, no flow spent
            before = max(k for k, s in enumerate(self.graph.seqs) if s < frame.seq)
            record.anchor = self.graph.seqs[before]
            record.anchor_from_cam = se3.inverse(self.graph.poses[before]) @ frame.tracked_world.to(self.device)
            self.frames.add(record)
            return Update()
        self.frames.add(record)
        if not self.initialised and start.static_for_long(self.graph, self.frames, self.params.init):
            self._force_initialise()  # a camera that has not moved for this long: a static map, now
        waiting = [s for s, f in self.frames.frames.items() if f.anchor is None]
        if self.initialised and len(waiting) > self.params.init.max_pending_frames:
            # no keyframe for this long (a fixed camera): frames are aligned to the last keyframe alone rather
            # than held for one that may never come
            for seq in waiting:
                self.frames.align(self.graph, seq)
            return Update(poses=pose_update(self.graph, self.frames, waiting))
        if not self.initialised or frame.seq > self.graph.seqs[-1]:
            return Update()  # aligned once the keyframe after it exists
        self.frames.align(self.graph, frame.seq)
        return Update(poses=pose_update(self.graph, self.frames, [frame.seq]))

    # --- keyframes -----------------------------------------------------------------------------------
    def _check(self, kf: KeyframeInput) -> np.ndarray:
        grey, hw = inputs.check_keyframe(kf)
        height, width = grey.shape
        if self.graph is None:
            self.graph = KeyframeGraph(grid_intrinsics(kf.intrinsics), hw, self.params.flow, self.device,
                                       self.params.focal_range, self.params.max_step_growth)
            self._size = (width, height)
            self._published = self.graph.intrinsics.cpu().numpy().copy()
        elif (width, height) != self._size:
            raise ValueError(f"keyframe {kf.seq}: working size {width}x{height} differs from {self._size}")
        elif kf.seq <= self.graph.seqs[-1]:
            raise ValueError(f"keyframe {kf.seq} is not newer than keyframe {self.graph.seqs[-1]}")
        return grey

    def _predict(self, prior: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        """Constant-velocity pose and a constant (or prior) disparity for a new keyframe."""
        g, dev = self.graph, self.device
        h, w = g.grid_hw
        if len(g) == 0:
            return torch.eye(4, dtype=torch.float64, device=dev), torch.ones(h, w, dtype=torch.float64, device=dev)
        pose = g.poses[-1]
        if len(g) >= 2 and self.initialised:
            pose = se3.orthonormalize(pose @ (se3.inverse(g.poses[-2]) @ g.poses[-1]))
        # the previous keyframe's map: neighbouring keyframes see similar structure (road near, sky far)
        disp = g.disparity[-1].clone() if self.initialised else torch.ones(h, w, dtype=torch.float64, device=dev)
        if prior is not None and self.metric:
            disp = torch.where(prior.to(dev) > 0, prior.to(dev), disp)
        return pose, disp

    def _lost_support(self, k: int, support: float) -> bool:
        """Keyframe ``k``'s flow supports less than ``relocalise.below_share`` of the grid, right after keyframes
        whose flow supported more than twice that (the median of the last six), and it comes early
        (``weak_keyframe_gap``): something fills the view. Where support is low all along (TartanAir's bare walls,
        0.1-0.3) a weak keyframe is the camera's own motion and is kept: made frames, those let the next keyframe's
        flow span ever more frames (TartanAir 1.3 -> 5.4 % of path)."""
        below = self.params.relocalise.below_share
        return (support < below and len(self._supports) >= 3 and float(np.median(self._supports)) > 2 * below
                and steps.early(self.graph, k, self.params.weak_keyframe_gap))

    def _in_burst(self, k: int) -> bool:
        """Keyframe ``k`` comes within ``burst_gap`` x the recent keyframe spacing: keyframes a frame apart where
        they came several apart are something moving through the view (its flow may be well supported: a rigid
        thing filling the view aligns like camera motion), and kept they become the window's gauge."""
        return steps.early(self.graph, k, self.params.burst_gap)

    def _window(self) -> list[int]:
        return self.graph.recent()[-self._window_size():]

    def _window_size(self) -> int:
        """Keyframes in the sliding window: a real-time stream's is shorter (its BA must keep up)."""
        return self.params.live_window if self._live else self.params.graph.window

    def _add_proximity(self, k: int) -> None:
        upkeep.add_proximity(self.graph, k, self._window(), self.params.graph)

    def _drop_unconstrained(self, window: list[int]) -> list[int]:
        """A BA result refused because one keyframe's step jumped (``upkeep.unconstrained``): that keyframe becomes
        a frame again and the BA runs once more. Returns the window after."""
        k = upkeep.unconstrained(self.graph, window)
        if k is None:
            return window
        seq = upkeep.to_frame(self.graph, self.frames, k)
        logger.info("keyframe the BA cannot constrain turned into a frame", extra={"seq": seq})
        window = self._window()
        self.graph.run(window, self.graph.pairs(window, self.params.graph.temporal_radius), self._ba_params(window),
                       codes_per_edge=self.params.window_ark_per_edge)
        return window

    def _remove_redundant(self) -> list[int] | None:
        """If the second-newest keyframe barely moved from the one before, make it a frame again.
        Returns the seqs of the window keyframes after removal, or None when nothing was removed."""
        k = upkeep.redundant(self.graph, self.params.graph)
        if k is None:
            return None
        upkeep.to_frame(self.graph, self.frames, k)
        return [self.graph.seqs[i] for i in self._window()]

    def _ba_params(self, window: list[int], base=None):
        if base is None:
            base = self.params.ba
            if self._live:
                base = dataclasses.replace(base, iterations=self.params.live_iterations)
        focal = (base.optimise_focal and len(window) >= self.params.focal_after
                 and len(self.graph) <= self.params.focal_until)
        return focal_ba(base, self.params) if focal else dataclasses.replace(base, optimise_focal=False)

    # --- initialisation (services/ba/frontend/start.py) ----------------------------------------------------
    def _try_initialise(self, force: bool = False) -> Update:
        p = self.params
        started = start.try_start(self.graph, self.frames, p, self._ba_params(list(range(len(self.graph)))), force)
        if started is None:
            return Update()
        if started == start.TURNING:
            self._calibrated = True  # no focal restarts: they start the map again from two views, and two views of
            # a turn have no depth to start from
        self.initialised = True
        self.graph.predict_flow = p.predict_flow
        self.metric = p.ba.alpha_disp > 0 and any(pr is not None for pr in self.graph.priors)
        update = self._update(list(range(len(self.graph))))
        self._retire()
        return update

    def _force_initialise(self) -> bool:
        """Start the map with what there is at end of stream; True when there was no parallax at all."""
        g = self.graph
        if len(g) > 1 and not start.has_parallax(g, self.params.init):
            init.start_static(g)
            self.initialised = True
            return True
        self._try_initialise(force=True)
        self.initialised = True
        return False

    # --- outputs -------------------------------------------------------------------------------------
    def _update(self, updated: list[int], every_frame: bool = False) -> Update:
        """Graph state for the keyframes at positions ``updated``; poses of those keyframes, of the frames
        anchored to them and of frames aligned now (all frames with ``every_frame``)."""
        g = self.graph
        aligned = []
        for seq in self.frames.pending(g):
            self.frames.align(g, seq)
            aligned.append(seq)
        anchors = {g.seqs[k] for k in updated}
        frame_seqs = list(self.frames.frames) if every_frame else self.frames.anchored_to(anchors) + aligned
        poses = pose_update(g, self.frames, sorted(set(frame_seqs)) + sorted(anchors))
        return Update(graph_update(g, updated, self.metric), poses, self._intrinsics_changed())

    def _intrinsics_changed(self) -> bool:
        """Whether the focal or the principal point moved (by a millionth of the focal) since the last update
        said so."""
        now = self.graph.intrinsics.cpu().numpy().copy()
        changed = bool(np.abs(now - self._published).max() > 1e-6 * abs(self._published[0]))
        self._published = now
        return changed

    @property
    def intrinsics(self) -> np.ndarray | None:
        """Current (refined) working-resolution intrinsics ``(4,)``, None before the first keyframe."""
        return None if self.graph is None else working_intrinsics(self.graph.intrinsics)

    @property
    def size(self) -> tuple[int, int]:
        """Working (width, height)."""
        return self._size
