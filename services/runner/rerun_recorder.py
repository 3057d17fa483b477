"""``kmvipe run --rerun``: the runner's Rerun recorder, on the bus beside the runner's own observer.

It subscribes to the stream's frames, keyframes, poses and intrinsics; the Zenoh callbacks only queue them and one
worker thread logs (Rerun's time is per thread, and a slow sink must not hold up Zenoh). The map comes from the
mapstore's export queryable (the chunk protocol of :class:`services.query_api.mapclient.MapClient`) every
``map_every_s`` and once more at end of stream; query highlights are the gateway's own answers: at end of stream
each ``--rerun-query`` text is posted to ``/v1/streams/<s>/query`` (the text encoder lives in the gateway, so a run
without it, or whose map answers no text, logs the reason instead).
"""
from __future__ import annotations

import logging
import os
import queue
import threading
import time
import uuid
from typing import NamedTuple

import httpx
import numpy as np

from ..common import keys
from ..common.bus import Bus, Delivery
from ..common.errors import KmVipeError
from ..common.schema import Frame, Intrinsics, Keyframe, Poses
from ..query_api.mapclient import MapClient
from . import rerun_log as rl

log = logging.getLogger(__name__)
MAP_TIMEOUT_S = 10.0  # one export chunk; a busy mapstore at end of stream answers in well under this
QUERY_TIMEOUT_S = 60.0  # the gateway's first text query may load its text model
QUERY_ATTEMPTS = 3
CHUNK_POINTS = 200_000  # as the gateway's export_chunk_points
FLUSH_TIMEOUT_S = 30.0  # an unreachable live viewer: Rerun gives up on it, the file sink is complete anyway
_STOP = object()


class _FrameSeen(NamedTuple):
    """A frame whose image is not logged: what the frustum needs of it."""

    seq: int
    width: int
    height: int
    intrinsics: np.ndarray | None


class _KeyframeSeen(NamedTuple):
    seq: int


class RerunRecorder:
    """Records one stream of a run; :meth:`close` logs the final map, trajectory and answers and ends the file."""

    def __init__(self, settings: rl.RerunSettings, bus: Bus, stream: str, gateway_url: str | None):
        rr = rl.load_rerun()
        self.settings, self.stream, self.gateway_url = settings, stream, gateway_url
        self.rec = rr.RecordingStream("kmvipe", recording_id=uuid.uuid4())
        self.rec.set_sinks(*rl.sinks(settings))
        self.rec.log(*rl.world(), static=True)
        self.maps = MapClient(bus, MAP_TIMEOUT_S)
        self.poses: dict[int, np.ndarray] = {}  # seq → latest world_from_cam
        self._mapped: set[int] = set()  # frames mapping has posed: a later tracking pose does not replace theirs
        self.keyframe_seqs: set[int] = set()
        self.images = self.map_size = 0
        self.last_seq = 0
        self._frame_k: tuple[tuple[float, ...], tuple[int, int]] | None = None  # the source's hint, frame pixels
        self._ba_k: tuple[tuple[float, ...], tuple[int, int]] | None = None  # BA's estimate, working pixels
        self._frame_size: tuple[int, int] | None = None
        self._logged_k: tuple | None = None
        self._map_at = time.monotonic()
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._closed = False
        for topic in (keys.FRAME, keys.KEYFRAME, keys.POSE, keys.INTRINSICS):
            bus.subscribe(keys.topic(stream, topic), self._on_message)
        self._worker = threading.Thread(target=self._run, name="rerun-recorder", daemon=True)
        self._worker.start()

    # --- Zenoh threads: queue only --------------------------------------------------------------------------
    def _on_message(self, delivery: Delivery) -> None:
        msg = delivery.msg
        if isinstance(msg, Keyframe):  # only its seq is needed: its image and codes are not kept queued
            self._queue.put(_KeyframeSeen(msg.seq))
        elif isinstance(msg, Frame) and msg.seq % self.settings.image_every:  # no image logged: its size only
            self._queue.put(_FrameSeen(msg.seq, msg.width, msg.height, msg.intrinsics))
        else:
            self._queue.put(msg)

    # --- the worker -----------------------------------------------------------------------------------------
    def _run(self) -> None:
        while True:
            try:
                item = self._queue.get(timeout=0.5)
            except queue.Empty:
                item = None
            if item is _STOP:
                return
            try:
                if item is not None:
                    self._handle(item)
                if self.settings.map_every_s and time.monotonic() - self._map_at >= self.settings.map_every_s:
                    self._map_at = time.monotonic()
                    self._log_geometry(services_up=True)
            except Exception:  # the recording is an extra: a failure is logged, the run goes on
                log.exception("rerun recorder failed on a message", extra={"stream": self.stream})

    def _handle(self, item) -> None:
        if isinstance(item, _KeyframeSeen):
            self.keyframe_seqs.add(item.seq)
        elif isinstance(item, (_FrameSeen, Frame)):
            self._frame_size = (item.width, item.height)
            if item.intrinsics is not None:
                self._frame_k = (tuple(map(float, item.intrinsics)), self._frame_size)
            self._at(item.seq)
            self._log_pinhole()
            if isinstance(item, Frame):
                for entity in rl.frame_image(item):
                    self.rec.log(*entity)
                self.images += 1
        elif isinstance(item, Intrinsics):
            self._ba_k = (tuple(map(float, item.intrinsics)), (item.width, item.height))
            self._log_pinhole()
        elif isinstance(item, Poses):
            for seq, pose in zip(item.frame_seqs, item.poses):
                if item.tracked and int(seq) in self._mapped:  # as the runner's trajectory: mapping's pose stays
                    continue
                if not item.tracked:
                    self._mapped.add(int(seq))
                self.poses[int(seq)] = np.asarray(pose, np.float64)
                self._at(int(seq))
                self.rec.log(*rl.camera_pose(pose))

    def _at(self, seq: int) -> None:
        self.last_seq = max(self.last_seq, seq)
        self.rec.set_time(rl.TIMELINE, sequence=seq)

    def _log_pinhole(self) -> None:
        """The frustum, when the intrinsics in frame pixels changed: BA's estimate once there is one (refined
        through the run), else the source's calibration hint."""
        if self._frame_size is None or (self._ba_k is None and self._frame_k is None):
            return
        k, size = self._ba_k or self._frame_k
        k = rl.scale_intrinsics(np.array(k), size, self._frame_size)
        key = (tuple(np.round(k, 3)), self._frame_size)
        if key != self._logged_k:
            self._logged_k = key
            self.rec.log(*rl.pinhole(k, self._frame_size))

    def _log_geometry(self, services_up: bool) -> None:
        """The trajectory and keyframes as they stand, and the map when the mapstore can still be asked."""
        self.rec.set_time(rl.TIMELINE, sequence=self.last_seq)
        seqs = sorted(self.poses)
        if seqs:
            self.rec.log(*rl.trajectory(np.stack([self.poses[s] for s in seqs])))
        placed = [s for s in sorted(self.keyframe_seqs) if s in self.poses]
        if placed:
            self.rec.log(*rl.keyframes(np.stack([self.poses[s] for s in placed])))
        if services_up:
            self._log_map()

    def _log_map(self) -> None:
        try:
            first = self.maps.export_chunk(self.stream, 0, CHUNK_POINTS)
            chunks = [first] + [self.maps.export_chunk(self.stream, i, CHUNK_POINTS) for i in range(1, first.n_chunks)]
        except KmVipeError as exc:  # no map yet (no keyframe fused), or a mapstore busy past the timeout
            log.info("no map for the recording yet", extra={"stream": self.stream, "reason": str(exc)})
            return
        xyz = np.concatenate([c.xyz for c in chunks])
        if len(xyz):
            self.rec.log(*rl.map_points(xyz, np.concatenate([c.rgb for c in chunks]), self.settings.map_max_points))
            self.map_size = len(xyz)

    def _log_queries(self) -> dict[str, dict]:
        """Each query text's answer from the gateway (its regions and best points), or why there is none."""
        texts = list(self.settings.queries)
        if not texts:
            return {}
        if self.gateway_url is None:
            return dict.fromkeys(texts, {"error": "the gateway did not run (--skip query_api): no text queries"})
        headers = {"X-API-Key": os.environ["KMVIPE_QUERY_API_KEY"]} if os.environ.get("KMVIPE_QUERY_API_KEY") else {}
        for _ in range(QUERY_ATTEMPTS):  # 504: the mapstore was busy past the gateway's timeout; ask again
            try:
                r = httpx.post(f"{self.gateway_url}/v1/streams/{self.stream}/query", headers=headers,
                               json={"texts": texts, "top_k": self.settings.query_top_k}, timeout=QUERY_TIMEOUT_S)
            except httpx.HTTPError as exc:
                return dict.fromkeys(texts, {"error": f"the gateway did not answer: {exc}"})
            if r.status_code != 504:
                break
        if r.status_code != 200:
            is_json = r.headers.get("content-type", "").startswith("application/json")
            detail = r.json().get("detail", r.text) if is_json else r.text
            return dict.fromkeys(texts, {"error": f"the gateway answered {r.status_code}: {detail}"})
        answers = {}
        for result in r.json()["results"]:
            for entity in rl.query_answer(result):
                self.rec.log(*entity)
            answers[result["text"]] = {"regions": len(result["regions"]), "top_points": len(result["top_points"])}
        return answers

    # --- the runner's side -----------------------------------------------------------------------------------
    def close(self, services_up: bool) -> dict:
        """Log what is still queued, then (``services_up``: the stream ended with the services still running) the
        final map and the query answers, and end the recording. What the summary reports of it."""
        if self._closed:
            return {}
        self._closed = True
        self._queue.put(_STOP)
        self._worker.join()
        queries = {}
        try:
            self._log_geometry(services_up)
            queries = self._log_queries() if services_up else {}
        finally:
            try:
                self.rec.flush(timeout_sec=FLUSH_TIMEOUT_S)
            except Exception:  # noqa: BLE001 - an unreachable viewer must not fail the run; the file is still ended
                log.warning("the Rerun viewer did not take the whole recording",
                            extra={"viewer": self.settings.connect})
            self.rec.disconnect()
        return {"path": str(self.settings.path) if self.settings.path else None, "viewer": self.settings.connect,
                "images": self.images, "poses": len(self.poses), "keyframes": len(self.keyframe_seqs),
                "map_points": self.map_size, "queries": queries}


    def __enter__(self) -> "RerunRecorder":
        return self

    def __exit__(self, *exc) -> None:  # a run that failed: what was logged still makes a valid file
        self.close(services_up=False)


class NoRecorder:
    """A run without ``--rerun``."""

    def close(self, services_up: bool) -> dict:
        return {}

    def __enter__(self) -> "NoRecorder":
        return self

    def __exit__(self, *exc) -> None:
        pass


def open_recorder(settings: rl.RerunSettings | None, bus: Bus, stream: str,
                  gateway_url: str | None) -> RerunRecorder | NoRecorder:
    """The recorder of a run (subscribed on ``bus`` before the source starts), or none without ``--rerun``."""
    return NoRecorder() if settings is None else RerunRecorder(settings, bus, stream, gateway_url)
