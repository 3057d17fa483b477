"""The gateway's state: bus, mapstore client, language path, example backbone, latest poses per stream.

Every method here blocks (Zenoh, torch); the HTTP routes call them from a worker thread.
"""
from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass

import numpy as np

from ..common import keys
from ..common.bus import Bus, Delivery
from ..common.errors import KmVipeError, ModelError, ServiceTimeout
from ..common.models import ModelStore
from ..common.schema import MapAnswer, MapSegment, Poses
from .config import QuerySettings
from .core.answers import QueryResult, RegionParams, group_answer
from .core.trajectory import PoseBook, Trajectory
from .mapclient import MapClient, MapServiceError, QueryOptions, StreamNotFound
from .textpath import SpaceMismatch, TextPath

log = logging.getLogger(__name__)
SERVICES = ("ingest", "features", "ba", "mapstore", "query_api")


class ExampleUnavailable(KmVipeError):
    """Query by example cannot run (backbone missing or not the map's)."""


@dataclass(frozen=True)
class Answer:
    """A scored query: per text, its regions and top points; optional per-point scores (Q, N)."""

    results: list[QueryResult]
    space: str  # the embedding space the vectors were scored in (the map's backbone)
    n_points: int
    all_scores: np.ndarray | None


class Gateway:
    def __init__(self, cfg: QuerySettings, bus: Bus, text: TextPath | None = None, backbone=None):
        self.cfg, self.bus = cfg, bus
        self.maps = MapClient(bus, cfg.timeout_s)
        self.text = text or TextPath(cfg)
        self._backbone = backbone
        self._backbone_lock = threading.Lock()
        self._poses: dict[str, PoseBook] = {}  # the current session's trajectory of each stream
        self._pose_sessions: dict[str, str] = {}
        self._poses_lock = threading.Lock()
        self._spaces: dict[tuple[str, str], tuple[float, str]] = {}  # (stream, session) → (time, backbone space)
        self._spaces_lock = threading.Lock()
        bus.subscribe(keys.topic("*", keys.POSE), self._on_pose, expect=[Poses])

    # -- poses ------------------------------------------------------------------------------------------
    def _on_pose(self, delivery: Delivery) -> None:
        msg = delivery.msg
        assert isinstance(msg, Poses)
        with self._poses_lock:
            current = self._pose_sessions.get(msg.stream, "")
            if msg.session and msg.session != current:
                if msg.session < current:  # a late pose of an earlier session (ids sort by start time)
                    return
                self._poses.pop(msg.stream, None)  # a new session: its own world frame, its own trajectory
                self._pose_sessions[msg.stream] = msg.session
            book = self._poses.setdefault(msg.stream, PoseBook(self.cfg.trajectory_capacity))
            book.update(msg.frame_seqs, msg.stamps_ns, msg.poses, msg.final)

    def trajectory(self, stream: str) -> Trajectory | None:
        """Every frame's latest pose: the mapstore's record of the stream (it outlives this process), with what
        this gateway saw on the bus after it; this gateway's own poses alone when no mapstore answers."""
        stored = self._stored_trajectory(stream)
        with self._poses_lock:
            book = self._poses.get(stream)
            seen = book.trajectory() if book is not None else None
            session = self._pose_sessions.get(stream, "")
        if stored is None or (session and stored.session and stored.session != session):
            return seen
        merged = PoseBook()
        if seen is not None:
            merged.update(seen.seqs, seen.stamps_ns, seen.poses)
        merged.update(stored.frame_seqs, stored.stamps_ns, stored.poses)  # the mapstore's keep mapping's revisions
        return merged.trajectory() if len(merged) else None

    def _stored_trajectory(self, stream: str) -> Poses | None:
        try:
            return self.maps.trajectory(stream)
        except (StreamNotFound, ServiceTimeout, MapServiceError) as exc:
            log.debug("no stored trajectory; the poses seen here answer", extra={"stream": stream, "error": str(exc)})
            return None

    def pose_streams(self) -> dict[str, int]:
        with self._poses_lock:
            return {s: len(b) for s, b in self._poses.items()}

    # -- queries ----------------------------------------------------------------------------------------
    def ask(self, stream: str, vectors: np.ndarray, space: str, opts: QueryOptions, session: str = "") -> Answer:
        """Score (Q, D) vectors in ``space`` against the map of ``stream`` (of an earlier ``session``'s map)."""
        ans: MapAnswer = self.maps.query(stream, vectors, space, opts, session)
        results = group_answer(len(vectors), ans.region_query, ans.region_score, ans.region_centroid,
                               ans.region_box_min, ans.region_box_max, ans.region_count, ans.point_query,
                               ans.point_xyz, ans.point_score, RegionParams())
        return Answer(results, space, int(ans.n_points), ans.all_scores)

    def map_space(self, stream: str, session: str = "") -> str:
        """The map's backbone space (from its stats, remembered for ``cfg.space_cache_s``)."""
        now = time.monotonic()
        with self._spaces_lock:
            hit = self._spaces.get((stream, session))
        if hit is not None and now - hit[0] < self.cfg.space_cache_s:
            return hit[1]
        space = self.maps.stats(stream, session).backbone
        with self._spaces_lock:
            self._spaces[(stream, session)] = (now, space)
        return space

    def text_vectors(self, stream: str, texts: list[str], session: str = "") -> tuple[np.ndarray, str]:
        """(Q, D) vectors of ``texts`` in the map's space."""
        space = self.map_space(stream, session)
        return self.text.embed(texts, space), space

    def query_text(self, stream: str, texts: list[str], opts: QueryOptions, session: str = "") -> Answer:
        vectors, space = self.text_vectors(stream, texts, session)
        return self.ask(stream, vectors, space, opts, session)

    def segment(self, stream: str, texts: list[str], session: str = "") -> MapSegment:
        vectors, space = self.text_vectors(stream, texts, session)
        return self.maps.segment(stream, vectors, space, session)

    def session_trajectory(self, stream: str, session: str) -> Trajectory | None:
        """The trajectory the mapstore recorded for an earlier ``session`` of the stream (its map's world frame)."""
        stored = self.maps.trajectory(stream, session)
        book = PoseBook()
        book.update(stored.frame_seqs, stored.stamps_ns, stored.poses)
        return book.trajectory() if len(book) else None

    def query_example(self, stream: str, image: np.ndarray, box=None, mask=None, opts=QueryOptions()) -> Answer:
        """Image (H, W, 3) uint8 RGB and a pixel box (x0, y0, x1, y1) or (H, W) bool mask → the answer."""
        # the backbone's runtime loads with its first example: a gateway never asked for one runs without it
        from ..common.models.backbones import normalise_rgb
        from .core.example import box_mask, fit_to_patches, pooled_feature

        space = self.map_space(stream)
        backbone = self.backbone()
        if space and backbone.output_space != space:
            raise SpaceMismatch(f"this map's features are in '{space}' but the example backbone "
                                f"'{backbone.name}' writes into '{backbone.output_space}'; set KMVIPE_QUERY_BACKBONE "
                                "to the backbone the features service used")
        if mask is None:
            mask = box_mask(image.shape[0], image.shape[1], box)
        img, m = fit_to_patches(image, mask, backbone.patch_size, self.cfg.example_max_side)
        feats = backbone(normalise_rgb(img))[0]  # (C, h, w)
        return self.ask(stream, pooled_feature(feats, m)[None], space, opts)

    def backbone(self):
        with self._backbone_lock:
            if self._backbone is None:
                from ..common.models.loaders import load_backbone

                try:
                    self._backbone = load_backbone(self.cfg.backbone, ModelStore(self.cfg.models_dir), self.cfg.device)
                except ModelError as exc:
                    raise ExampleUnavailable(f"query by example needs the backbone '{self.cfg.backbone}': {exc}") from exc
            return self._backbone

    # -- discovery --------------------------------------------------------------------------------------
    def streams(self) -> dict[str, dict]:
        """Every known stream: those a mapstore serves (with stats) and those with poses."""
        out: dict[str, dict] = {}
        for name, st in self.maps.all_stats(self.cfg.alive_timeout_s).items():
            out[name] = {"map": {"keyframes": st.keyframes, "points": st.points, "voxels": st.voxels,
                                 "backbone": st.backbone, "pca_version": st.pca_version, "metric": st.metric,
                                 "session": st.session}}
        for name, n in self.pose_streams().items():
            out.setdefault(name, {"map": None})["poses"] = n
        with self._poses_lock:
            sessions = dict(self._pose_sessions)
        for name, entry in out.items():
            entry.setdefault("poses", 0)
            entry["session"] = sessions.get(name) or (entry["map"] or {}).get("session", "")
        return out

    def health(self) -> dict[str, list[str]]:
        """Alive instances per service (every known service listed, empty when down)."""
        alive = self.bus.alive(self.cfg.alive_timeout_s)
        return {name: sorted(alive.get(name, [])) for name in (*SERVICES, *sorted(set(alive) - set(SERVICES)))}

