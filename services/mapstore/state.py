"""The mapstore's state: the durable store and the in-memory map, kept in step.

Every change is committed to the store first and applied to the map only after the commit, so the map
(what queries see) never holds anything a restart would not reload.

PCA versions: keyframes are stored with the codes and version they arrived with; the fused map is kept in the
latest basis version (the one queries are scored with). A newer basis re-sums the fused codes through one
affine map per keyframe version (`KeyframeMap.set_code_space`); a keyframe whose basis has not arrived yet is
stored and held (not fused, not counted as in the map) until it does — also across a restart, since bases are
stored too. A restart converts each stored keyframe from its own version to the latest stored one, which is
what the uninterrupted run did, so both give the same map.

Codes after geometry: features sends a keyframe's geometry at once (a ``Keyframe`` without codes) and its codes
later (``KeyframeCodes``). A keyframe without codes is committed and fused for geometry at once (points, colours,
carving depth evidence; no code sums). Its codes are committed when they come and the keyframe is re-fused with
them; codes whose keyframe has not come yet (another key: Zenoh orders per key only) wait in memory for it, and
codes whose basis has not come yet are committed but wait for the basis before they enter the map (the keyframe
stays in it for geometry meanwhile; a restart in between reloads it with its codes, held for the basis like any
stored keyframe whose basis is unknown). A ``Keyframe`` that carries its codes works as before.

Flat memory: each ba graph lists the keyframes ba still holds; a keyframe older than the newest of them that it
does not list has left ba's graph for good (ba keeps its newest ``keep_keyframes`` and sometimes drops a
redundant one from the middle; the landmarks it keeps past them are not listed: their poses are fixed, final). Such a keyframe is *settled* once its codes are in (or it came from a real-time
stream, whose codes may never come) and no codes wait for its basis; after every re-fusion the oldest settled
keyframes whose carving window is settled too are folded (`KeyframeMap.fold`; the policy is
services/mapstore/folding_policy.py): recorded in the store's
``folded`` table first, then their sums frozen and their arrays dropped. Graph updates, repeats and codes for a
folded keyframe stay out of the map (codes are still committed). Beyond ``max_live_keyframes`` held, keyframes
that have left ba's graph are folded even without their codes. A restart streams the store in id order
(`MapStore.iter_keyframes`), folding the recorded keyframes as soon as their window is loaded.
"""

from __future__ import annotations

import logging
import threading
import time
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Iterator

import cv2
import numpy as np

from services.common.own_pages import own_pages
from services.mapstore.answer_cache import AnswerCache
from services.mapstore.config import MapstoreSettings
from services.mapstore.core.geometry import sample_cell_colours
from services.mapstore.core.keyframe import KeyframeContent, KeyframeDepth
from services.mapstore.core.map import KeyframeMap, code_maps_to_latest
from services.mapstore.core.scoring import PcaBasis
from services.mapstore.export import FoldedExports
from services.mapstore.folding_policy import FoldingPolicy
from services.mapstore.frozen_files import FileSums
from services.mapstore.poselog import PoseLog
from services.mapstore.sessions import archive_other_session
from services.mapstore.store import MapStore, Thumbnail

if TYPE_CHECKING:
    from services.mapstore.core.index import ScoringIndex

log = logging.getLogger(__name__)
RESTART_PAGE = 64  # keyframes read from the store at a time when a restart streams them


def make_thumbnail(image: np.ndarray, side: int, quality: int) -> Thumbnail | None:
    """(H, W, 3) uint8 RGB → JPEG with longest side ``side`` (never enlarged); None when ``side`` is 0."""
    if side <= 0:
        return None
    h, w = image.shape[:2]
    scale = min(1.0, side / max(h, w))
    size = (max(1, round(w * scale)), max(1, round(h * scale)))
    small = cv2.resize(image, size, interpolation=cv2.INTER_AREA) if scale < 1.0 else image
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(small, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, quality])
    return Thumbnail(buf.tobytes(), size[0], size[1]) if ok else None


class MapState(FoldingPolicy):
    """Store + map + the scoring index of the latest map revision. Methods are thread-safe."""

    def __init__(self, cfg: MapstoreSettings, session: str | None = None) -> None:
        """``session``: the stream's session this map is of (a map of another session at the path is moved
        aside first); None: not known yet (:meth:`adopt_session`)."""
        self.cfg = cfg
        self.lock = threading.RLock()
        path = Path(cfg.db_path.format(stream=cfg.stream))
        if session:
            archive_other_session(path, session)
        self.store = MapStore(path, synchronous=cfg.synchronous)
        stored = self.store.load_static()
        self.session = session or stored.meta.get("session", "")
        if session and stored.meta.get("session") != session:
            self.store.set_meta({"session": session})
        voxel = float(stored.meta["voxel_size"]) if "voxel_size" in stored.meta else None
        self.frozen_files = FileSums(path) if cfg.frozen_sums == "files" else None
        self.map = KeyframeMap(cfg.map_params(), voxel_size=voxel, versioned=True, frozen_store=self.frozen_files)
        self.bases: dict[int, PcaBasis] = stored.bases
        if self.bases:
            self.map.set_code_space(*code_maps_to_latest(self.bases))
        self.metric = stored.meta.get("metric") == "1"
        self.intrinsics: dict[int, np.ndarray] = {}  # live keyframes' intrinsics as they arrived
        self.pose_log = PoseLog()  # every frame's pose, for the trajectory (services/mapstore/poselog.py)
        self.realtime: set[int] = set()  # live keyframes of a real-time stream: their codes may never come
        # codes not in the map yet: their keyframe has not arrived (memory only), or their basis (committed)
        self.waiting_codes: dict[int, tuple[int, np.ndarray]] = {}  # kf_id -> (pca_version, (h, w, K) float16)
        self._graph_seqs: set[int] = set()  # the keyframes ba's latest graph holds ...
        self._graph_max: int | None = None  # ... and the newest of them (None: no graph since the start)
        self.late_codes = 0  # codes that came for a keyframe already folded (committed, not in the map)
        self.re_fusion = {"refreshes": 0, "keyframes": 0, "seconds": 0.0}  # the re-fusions' work so far (logged)
        # folded keyframes are final: their depth maps and images go to export_dir as they fold, so the end of
        # stream writes only the keyframes still live, the point cloud and the COLMAP model (export_folded)
        self.folded_exports = FoldedExports(Path(cfg.export_dir) if cfg.export_dir else None)
        self._load()
        self._index: tuple[int, int, ScoringIndex] | None = None  # (map revision, basis version, index)
        self.answers = AnswerCache(cfg.answer_cache)  # findings of recent queries on that index
        self._deferred: bool | None = None  # None outside batch(); inside, the metric flag of the last write
        self._unfused: bool | None = None  # a batch left its changes unfused: the metric flag they carry
        # end of stream: ba's EOS is held until its final graph has been applied (or eos_wait_s passed)
        self.final_keyframes: set[int] | None = None
        self.pending_eos = None
        self.eos_deadline = 0.0
        self.final_export_s: float | None = None  # the export ran on the final graph (before ba's EOS), in seconds
        log.info("map loaded", extra={"stream": cfg.stream, "keyframes": self.keyframe_count(),
                                      "folded": self.map.folded_count, "held": len(self.map.held),
                                      "without_codes": self.without_codes_count(),
                                      "voxels": len(self.map.fused().keys)})

    def _load(self) -> None:
        """Stream the stored keyframes into the map in id order; the folded ones are folded again (as they were
        folded: with codes, geometry only, or nothing) once their carving window is loaded."""
        marked: list[int] = []  # folded in the store, loaded, waiting for their window
        for records, last in self.store.iter_keyframes(RESTART_PAGE):
            for r in records:
                content = r.content
                if r.folded == 1 and content is not None:  # folded for geometry only: without its codes
                    content = KeyframeContent(r.kf_id, content.t_ns, None, content.colours, content.image_hw, -1)
                if content is not None:
                    self.map.add_content(content)
                if r.folded != 0:  # 0: folded with no contribution (no pose, depth or basis then)
                    if r.depth is not None:
                        self.map.set_depth(r.kf_id, r.depth)
                    if r.pose is not None:
                        self.map.set_pose(r.kf_id, r.pose)
                if r.folded is not None:
                    marked.append(r.kf_id)
                    continue
                if r.intrinsics is not None:
                    self.intrinsics[r.kf_id] = r.intrinsics
                if r.realtime:
                    self.realtime.add(r.kf_id)
            self.map.refresh()
            n = 0
            while n < len(marked) and (last or self.map.fold_window_complete(marked[n])):
                n += 1
            self.map.fold(marked[:n])
            del marked[:n]

    def close(self) -> None:
        self.store.close()
        if self.frozen_files is not None:
            self.frozen_files.close()

    def for_session(self, session: str) -> "MapState":
        """The state for a message of ``session`` (a mapstore pinned to one stream learns it from its messages):
        this one, naming its session if it had none and is empty; else a fresh map, the other session's moved
        aside (a ``kmvipe run`` into an existing output folder starts a new map instead of extending the old one)."""
        if not session or session == self.session:
            return self
        if not self.session and self.keyframe_count() == 0:
            self.session = session
            self.store.set_meta({"session": session})
            return self
        self.close()
        return MapState(self.cfg, session)

    def trajectory(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every frame pose of the stream so far: (N,) seqs, (N,) stamps, (N, 4, 4) world_from_cam."""
        self.pose_log.flush(self.store)
        return self.store.frame_poses()

    # ----- writes ---------------------------------------------------------------------------------
    def add_keyframe(self, kf_id: int, t_ns: int, image: np.ndarray, codes: np.ndarray | None,
                     intrinsics: np.ndarray, pca_version: int, realtime: bool = False) -> None:
        """Commit then apply a keyframe: image (H, W, 3) uint8 RGB, codes (H/8, W/8, K) or None (geometry now,
        codes later: `add_codes`); ``realtime``: from a real-time stream, whose keyframes may never get codes."""
        colours = sample_cell_colours(image)
        jpeg = None
        if self.cfg.store_images:
            ok, buf = cv2.imencode(".jpg", cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
            jpeg = buf.tobytes() if ok else None
        thumbnail = make_thumbnail(image, self.cfg.thumbnail_side, self.cfg.thumbnail_quality)
        with self.lock:
            if self.map.is_folded(kf_id):  # a repeat of a keyframe folded long ago: it is final
                log.info("keyframe already folded: ignored", extra={"stream": self.cfg.stream, "seq": kf_id})
                return
            waiting = False
            if codes is not None:  # the keyframe carries its codes (as before codes had their own message)
                self.waiting_codes.pop(kf_id, None)
            elif kf_id in self.waiting_codes:  # its codes overtook it
                pca_version, codes = self.waiting_codes[kf_id]
                waiting = True
            else:  # geometry only; a repeat of a keyframe whose codes are in keeps them
                old = self.map.contents.get(kf_id)
                keep = old is not None and old.has_codes and old.grid_shape == colours.shape[:2]
                codes, pca_version = (old.codes, old.pca_version) if keep else (None, -1)
            codes = None if codes is None else own_pages(codes, np.float16)  # kept while live: off the heap
            content = KeyframeContent(kf_id, t_ns, codes, colours, image.shape[:2], pca_version)
            self.store.put_keyframe(content, intrinsics, jpeg, realtime, thumbnail)
            self.intrinsics[kf_id] = np.asarray(intrinsics, np.float64)
            if realtime:
                self.realtime.add(kf_id)
            if waiting and pca_version not in self.bases:  # geometry now, the codes once their basis is in
                self.map.add_content(KeyframeContent(kf_id, t_ns, None, colours, image.shape[:2], -1))
                self._log_waiting_basis(kf_id, pca_version)
            else:
                self.waiting_codes.pop(kf_id, None)
                self.map.add_content(content)
                if codes is not None and pca_version not in self.bases:  # its basis may still be on the way
                    log.info("keyframe held until its PCA basis arrives",
                             extra={"stream": self.cfg.stream, "seq": kf_id, "pca_version": pca_version})
            # ba's graph may have overtaken this keyframe on the bus (they come from different services)
            self._refresh(self.metric)

    def add_codes(self, kf_id: int, pca_version: int, codes: np.ndarray) -> None:
        """Commit then apply the codes (h, w, K) of keyframe ``kf_id`` (coded with basis ``pca_version``): it is
        re-fused with them. Codes before their keyframe wait (in memory) for it; codes before their basis are
        committed and wait for it (the keyframe stays in the map for geometry meanwhile)."""
        codes = own_pages(codes, np.float16)  # kept while the keyframe is live: off the heap
        with self.lock:
            if self.map.is_folded(kf_id):  # folded before its codes came (real-time, or past max_live_keyframes)
                self.store.put_codes(kf_id, pca_version, codes)
                self.late_codes += 1
                log.info("codes of a folded keyframe: committed, not in the map",
                         extra={"stream": self.cfg.stream, "seq": kf_id})
                return
            content = self.map.contents.get(kf_id)
            if content is None:  # another key than the keyframe's: the codes may overtake it
                self.waiting_codes[kf_id] = (pca_version, codes)
                log.info("codes wait for their keyframe", extra={"stream": self.cfg.stream, "seq": kf_id})
                return
            if codes.ndim != 3 or codes.shape[:2] != content.grid_shape:
                raise ValueError(f"codes {codes.shape} of keyframe {kf_id} do not fit its {content.grid_shape} grid")
            if content.has_codes and content.pca_version == pca_version and np.array_equal(content.codes, codes):
                return  # a repeat
            self.store.put_codes(kf_id, pca_version, codes)
            if pca_version not in self.bases:
                self.waiting_codes[kf_id] = (pca_version, codes)
                self._log_waiting_basis(kf_id, pca_version)
                return
            self.waiting_codes.pop(kf_id, None)
            self.map.set_codes(kf_id, codes, pca_version)
            self._refresh(self.metric)

    def _log_waiting_basis(self, kf_id: int, pca_version: int) -> None:
        log.info("codes wait for their PCA basis (the keyframe is fused for geometry meanwhile)",
                 extra={"stream": self.cfg.stream, "seq": kf_id, "pca_version": pca_version})

    def _apply_waiting_codes(self) -> None:
        """Put the waiting codes whose keyframe and basis are both in into the map (lock held)."""
        for kf_id, (version, codes) in list(self.waiting_codes.items()):
            if kf_id in self.map.contents and version in self.bases:
                del self.waiting_codes[kf_id]
                self.map.set_codes(kf_id, codes, version)

    def add_basis(self, basis: PcaBasis) -> None:
        """Commit then apply a basis: the fused map moves to the latest version, held keyframes it frees are fused."""
        with self.lock:
            known = self.bases.get(basis.version)
            if known is not None and np.array_equal(known.mean, basis.mean) and \
                    np.array_equal(known.components, basis.components):
                return  # a repeat (features' late-joiner reply, or a re-published message)
            self.store.put_basis(basis)
            self.bases[basis.version] = basis
            self.map.set_code_space(*code_maps_to_latest(self.bases))
            self._apply_waiting_codes()
            self._refresh(self.metric)
            if self.map.held:
                log.info("keyframes held for their PCA basis", extra={"stream": self.cfg.stream,
                                                                      "held": self.map.held[:10]})

    def update_graph(self, poses: dict[int, np.ndarray], depths: dict[int, KeyframeDepth], metric: bool) -> int:
        """Commit then apply poses and depths; re-fuse what changed. Returns the number of re-fused keyframes.
        ``poses`` names every keyframe ba holds (a graph's kf_seqs): older keyframes it does not name have left
        ba's graph. Poses and depths of folded keyframes are left out (they are final)."""
        with self.lock:
            if poses:
                self._graph_seqs, self._graph_max = set(poses), max(poses)
            poses = {k: p for k, p in poses.items() if not self.map.is_folded(k)}
            depths = {k: d for k, d in depths.items() if not self.map.is_folded(k)}
            self.store.put_graph(poses, depths)
            for kf_id, depth in depths.items():
                self.map.set_depth(kf_id, depth)
            for kf_id, pose in poses.items():
                self.map.set_pose(kf_id, pose)
            return self._refresh(metric)

    @contextmanager
    def batch(self, refresh: bool = True) -> Iterator[None]:
        """Writes inside are committed one by one as always, but re-fused once at the end: a burst of graph
        updates or bases costs one re-fusion of what changed, not one per message. ``refresh`` False: not even
        then; what changed waits for the next batch that re-fuses, or :meth:`refresh`."""
        with self.lock:
            self._deferred = self._unfused if self._unfused is not None else self.metric
        try:
            yield
        finally:
            with self.lock:
                metric, self._deferred = self._deferred, None
                if refresh:
                    self._unfused = None
                    self._refresh(metric)
                else:
                    self._unfused = metric

    def refresh(self, now: bool = False) -> int:
        """Re-fuse what batches left waiting (:meth:`batch`), if anything; the number of keyframes re-fused.
        ``now``: everything committed, inside a batch too (the export, which may run while a batch handles ba's
        EOS, writes the map as it stands)."""
        with self.lock:
            if now and self._deferred is not None:
                metric, self._deferred, self._unfused = self._deferred, None, None
                try:
                    return self._refresh(metric)
                finally:  # the batch goes on; nothing it committed so far is left for its end
                    self._deferred = self.metric
            if self._unfused is None:
                return 0
            metric, self._unfused = self._unfused, None
            return self._refresh(metric)

    def _refresh(self, metric: bool) -> int:
        """Re-fuse what changed (lock held); persist the voxel size once known. Returns keyframes re-fused (0
        inside `batch`, which re-fuses at its end)."""
        if self._deferred is not None:
            self._deferred = metric
            return 0
        had_voxel = self.map.voxel_size is not None
        began = time.perf_counter()
        report = self.map.refresh()
        if report.refreshed:
            self.re_fusion["refreshes"] += 1
            self.re_fusion["keyframes"] += len(report.refreshed)
            self.re_fusion["seconds"] += time.perf_counter() - began
        meta = {}
        if not had_voxel and self.map.voxel_size is not None:
            meta["voxel_size"] = repr(float(self.map.voxel_size))
        if metric != self.metric:
            self.metric = metric
            meta["metric"] = "1" if metric else "0"
        if meta:
            self.store.set_meta(meta)
        self._fold()
        return len(report.refreshed)

    # ----- reads ----------------------------------------------------------------------------------
    def committed_seq(self) -> int:
        """The highest keyframe seq committed (-1: none): what the mapstore reports as its progress."""
        with self.lock:
            return max(max(self.map.contents, default=-1), self.map.folded_upto)

    def has_codes(self, kf_id: int) -> bool:
        """Whether keyframe ``kf_id`` is in the map with its codes (folded ones too)."""
        with self.lock:
            if self.map.is_folded(kf_id):
                return self.store.folded_mode(kf_id) == 2
            content = self.map.contents.get(kf_id)
            return content is not None and content.has_codes

    def keyframe_count(self) -> int:
        """Keyframes in the map: held in memory plus folded."""
        with self.lock:
            return len(self.map.contents) + self.map.folded_count

    def without_codes_count(self) -> int:
        """Keyframes in the map without codes: live ones whose codes have not come, and ones folded without."""
        with self.lock:
            return len(self.map.without_codes) + self.map.folded_without_codes

    def basis(self) -> PcaBasis:
        if not self.bases:
            raise LookupError("no PCA basis received yet: the map cannot score queries")
        return self.bases[max(self.bases)]

    def index(self) -> ScoringIndex:
        """Scoring index of the current fused map under the latest basis (rebuilt when either changes)."""
        with self.lock:
            basis = self.basis()
            if self._index is None or self._index[:2] != (self.map.revision, basis.version):
                from services.mapstore.core.index import ScoringIndex  # torch: loaded by the first query only

                fused = self.map.fused()  # voxels only keyframes without codes saw have none: absent, not scored
                self._index = (self.map.revision, basis.version,
                               ScoringIndex(fused.codes, basis, self.map.params.scoring.device,
                                            valid=None if fused.code_weight is None else fused.code_weight > 0))
            return self._index[2]
