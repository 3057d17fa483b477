"""The frontend's work beyond its sliding window: refinement in mapping's spare time and the end of stream.

A live stream's spare time solves tracked frames again with mapping's own flow (:meth:`refine_frame`); a lossless
stream's runs a BA over the held keyframes every ``background_ba_every`` keyframes (:meth:`refine_globally`). At the
end of a stream the BA over every keyframe still held settles them (:meth:`settle_keyframes`: their final graph,
which the mapstore can export at once) and then the frames are solved again against them (:meth:`solve_frames`).
A mixin of :class:`~services.ba.frontend.frontend.Frontend`, whose state it works on.
"""
from __future__ import annotations

import logging
import time
from dataclasses import replace
from typing import Callable

from services.ba.core.ba import BAResult
from services.ba.frontend.updates import Update, graph_update, pose_update

logger = logging.getLogger(__name__)


def time_bound(bound_s: float, clock: Callable[[], float] = time.monotonic) -> Callable[[], bool] | None:
    """A solve's ``should_stop`` (asked after every iteration; see ``run_ba``) that keeps it within ``bound_s``
    seconds from now: True once another iteration, as long as the last one, would end past the bound (None: no
    bound). Stopping only once the bound had passed overran it by up to an iteration (the 10,000-frame stream's
    end-of-stream BA: 2.5 s for a 2 s bound)."""
    if bound_s <= 0:
        return None
    began = last = clock()

    def should_stop() -> bool:
        nonlocal last
        now = clock()
        iteration, last = now - last, now
        return now - began + iteration > bound_s

    return should_stop


class Refinement:
    """End of stream and spare-time refinement of :class:`~services.ba.frontend.frontend.Frontend`."""

    def finish(self) -> Update:
        """End of stream: :meth:`settle_keyframes` then :meth:`solve_frames`; the final state in one update."""
        settled = self.settle_keyframes()
        solved = self.solve_frames()
        return Update(settled.graph, solved.poses, settled.intrinsics_changed)

    def settle_keyframes(self) -> Update:
        """End of stream, first half: the BA over every keyframe still held; their final graph (no frame poses),
        which the mapstore can export while :meth:`solve_frames` runs."""
        g = self.graph
        if g is None or len(g) == 0:
            return Update()
        static = False
        if not self.initialised:
            static = self._force_initialise()
        began = time.monotonic()
        if len(g) > 1 and not static:
            self._global_ba(self._end_bound_s(), self._settle_span())
        logger.info("end of stream: keyframes final", extra={"keyframes": len(g),
                                                             "global_ba_s": round(time.monotonic() - began, 2)})
        return Update(graph_update(g, list(range(len(g))), self.metric), None, self._intrinsics_changed())

    def solve_frames(self) -> Update:
        """End of stream, second half (after :meth:`settle_keyframes`): the frames not aligned yet aligned, those
        held solved again against the final keyframes (bounded by ``final_align_s``); every frame's and keyframe's
        pose."""
        g = self.graph
        if g is None or len(g) == 0:
            return Update()
        began = time.monotonic()
        # frames after the last keyframe too: at the end no later keyframe will come to bracket them
        for seq in [s for s, f in self.frames.frames.items() if f.anchor is None]:
            self.frames.align(g, seq)
        self.frames.align_at_end(g, time.monotonic() + self.params.final_align_s, self.params.realign_focal_change)
        logger.info("end of stream: frames final", extra={"frames": len(self.frames.frames),
                                                          "frames_s": round(time.monotonic() - began, 2)})
        return Update(poses=pose_update(g, self.frames, sorted(self.frames.frames) + list(g.seqs)))

    def refine_globally(self) -> Update:
        """Background refinement (mapping's spare time, or on a lossless stream after a keyframe when ba sets the
        pace): once ``background_ba_every`` keyframes have joined since the last one, the end of stream's BA over
        the held keyframes, bounded to ``background_ba_s``, so the map outside the window is refined during the
        stream and the end of stream's own BA only settles it (bounded to ``settled_global_ba_s`` once one ran).
        It spans the newest held keyframes and the landmarks they reach, ``background_ba_keyframes`` (0:
        ``keep_keyframes``) of them together, and ``background_ba_edges`` edges at most when set
        (:meth:`_background_span`; the oldest held one is its gauge), so its memory and time are bounded by that.
        Every keyframe's pose and the maps of those it spanned in the update (empty when none is due, or the BA was
        refused). A live stream's mapping has seconds for it only between keyframes: its BA is bounded to
        ``live_background_ba_s`` (0: none), a few iterations that keep the live map's drift down (tracking aligns
        to it), and it does not count as one the end of stream may merely settle."""
        g, p = self.graph, self.params
        bound = p.live_background_ba_s if self._live else p.background_ba_s
        if (g is None or not self.initialised or (self._live and bound <= 0) or p.background_ba_every <= 0
                or self._since_global < p.background_ba_every
                or len(g) <= self._window_size()):
            return Update()
        self._since_global = 0
        self._background_bas += 0 if self._live else 1
        keyframes = self._background_span()
        began = time.monotonic()
        result = self._global_ba(bound, keyframes)
        accepted = result is not None
        logger.info("background BA", extra={"keyframes": len(keyframes), "edges": self._edge_count(keyframes),
                                            "accepted": accepted, "steps": len(result.costs) - 1 if accepted else 0,
                                            "without_codes": sum(g.codes[k] is None for k in keyframes),
                                            "seconds": round(time.monotonic() - began, 2)})
        return self._update(keyframes) if accepted else Update()

    def _background_span(self) -> list[int]:
        """The held keyframes a background BA spans: the newest ``background_ba_keyframes`` (0: ``keep_keyframes``),
        the landmarks their loop edges reach counted in. ba's memory high-water is this BA's (~0.4 MB per edge on a
        48x64 grid, held by the allocator after it), so once a camera comes round again the landmarks take the
        place of the oldest held keyframes instead of adding to it: 10,000 frames round a room went 1,056 ->
        1,271 MB after their first 1,000 frames as 15 landmarks joined (docs/BENCHMARKS.md). Its edges can be
        bounded the same way, by ``background_ba_edges`` (0: not bounded)."""
        g, p = self.graph, self.params
        budget = p.background_ba_keyframes if p.background_ba_keyframes > 0 else p.keep_keyframes
        recent = g.recent()
        linked = len(g.linked_landmarks(recent[-budget:]))
        span = recent[-max(budget - linked, p.graph.window):]
        if p.background_ba_edges <= 0:
            return span
        # and its edges: a revisit's loop edges add to a span's edges as its landmarks add to its keyframes. The
        # oldest keyframes leave until it fits (fewer keyframes never make more edges: a search over the start)
        first, last = 0, max(0, len(span) - p.graph.window)
        while first < last:
            mid = (first + last) // 2
            if self._edge_count(span[mid:]) <= p.background_ba_edges:
                last = mid
            else:
                first = mid + 1
        return span[first:]

    def _edge_count(self, keyframes: list[int]) -> int:
        """Edges of the global BA over ``keyframes`` (:meth:`_global_ba`: the landmarks they reach joined)."""
        g = self.graph
        return len(g.pairs(g.linked_landmarks(keyframes) + keyframes, self.params.graph.global_radius))

    def _settle_span(self) -> list[int] | None:
        """The keyframes the end-of-stream BA spans (None: every held one). Once background BAs ran, those that
        joined since the last one and a window before them (its oldest the gauge): the ones before were refined
        during the stream, and the first iteration over every held keyframe alone took 4.5 s at 100 keyframes,
        past the 2 s bound (``settle_all_keyframes`` restores it)."""
        g, p = self.graph, self.params
        if p.settle_all_keyframes or not self._background_bas:
            return None
        recent = g.recent()
        return recent[max(0, len(recent) - self._since_global - p.graph.window):]

    def _end_bound_s(self) -> float:
        """The end-of-stream BA's time bound (0: none): ``global_ba_s``, and ``settled_global_ba_s`` once
        background BAs ran during the stream, whichever is shorter."""
        bounds = [self.params.global_ba_s]
        if self._background_bas:
            bounds.append(self.params.settled_global_ba_s)
        return min((b for b in bounds if b > 0), default=0.0)

    def _global_ba(self, bound_s: float, keyframes: list[int] | None = None) -> BAResult | None:
        """The BA over ``keyframes`` (positions, the oldest the gauge; default every held keyframe but the
        landmarks) and the landmarks their loop edges reach, fixed with the gauge, with the global edge set, within
        ``bound_s`` seconds (:func:`time_bound`; 0: all its iterations); None when its result was refused."""
        g = self.graph
        keyframes = g.recent() if keyframes is None else keyframes
        landmarks = g.linked_landmarks(keyframes)
        params = self._ba_params(keyframes, self.params.global_ba)
        if landmarks:  # older than every held keyframe, so first in the span: the poses held fixed
            params = replace(params, fixed_poses=len(landmarks) + 1)
        span = landmarks + keyframes
        return g.run(span, g.pairs(span, self.params.graph.global_radius), params, time_bound(bound_s))

    def refine_frame(self) -> Update:
        """Mapping's spare time on a live stream, one frame per call; its revised pose in the update (empty when
        there is nothing to do). First a tracked frame whose reference keyframe has left the BA window (its depth
        settled), solved again with tracking's flow (~10 ms); else the oldest frame whose pose no flow of mapping's
        measured yet (anchored where tracking put it, or interpolated by time), with keyframes on both sides,
        aligned to them with mapping's own flow (~100 ms). Tracking's cheap flow leaves such frames ~2 cm off on the
        synthetic world where keyframes are at 3 mm."""
        g = self.graph
        if g is None or not self.initialised:
            return Update()
        settled = self.frames.resolvable(before=g.seqs[self._window()[0]])
        if settled:
            self.frames.resolve(g, settled[0])
            return Update(poses=pose_update(g, self.frames, settled[:1]))
        last = g.seqs[-1]
        seq = next((s for s in self.frames.unmeasured() if s < last), None)
        if seq is None:
            return Update()
        self.frames.measure(g, seq)
        return Update(poses=pose_update(self.graph, self.frames, [seq]))
