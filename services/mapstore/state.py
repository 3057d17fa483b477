"""The mapstore's state: the durable store and the in-memory map, kept in step.

Every change is committed to the store first and applied to the map only after the commit, so the map
(what queries see) never holds anything a restart would not reload.

PCA versions: keyframes are stored with the codes and version they arrived with; the fused map is kept in the
latest basis version (the one queries are scored with). A newer basis re-sums the fused codes through one
affine map per keyframe version (`KeyframeMap.set_code_space`); a keyframe whose basis has not arrived yet is
stored and held (not fused, not counted as in the map) until it does — also across a restart, since bases are
stored too. A restart converts each stored keyframe from its own version to the latest stored one, which is
what the uninterrupted run did, so both give the same map.
"""

from __future__ import annotations

import logging
import threading
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from services.mapstore.config import MapstoreSettings
from services.mapstore.core.geometry import sample_cell_colours
from services.mapstore.core.keyframe import KeyframeContent, KeyframeDepth
from services.mapstore.core.map import KeyframeMap, code_maps_to_latest
from services.mapstore.core.scoring import PcaBasis, ScoringIndex
from services.mapstore.store import MapStore

log = logging.getLogger(__name__)


class MapState:
    """Store + map + the scoring index of the latest map revision. Methods are thread-safe."""

    def __init__(self, cfg: MapstoreSettings) -> None:
        self.cfg = cfg
        self.lock = threading.RLock()
        self.store = MapStore(Path(cfg.db_path.format(stream=cfg.stream)), synchronous=cfg.synchronous)
        stored = self.store.load()
        voxel = float(stored.meta["voxel_size"]) if "voxel_size" in stored.meta else None
        self.map = KeyframeMap(cfg.map_params(), voxel_size=voxel, versioned=True)
        self.bases: dict[int, PcaBasis] = stored.bases
        if self.bases:
            self.map.set_code_space(*code_maps_to_latest(self.bases))
        self.metric = stored.meta.get("metric") == "1"
        self.intrinsics = stored.intrinsics
        for kf_id, content in stored.contents.items():
            self.map.add_content(content)
        for kf_id, depth in stored.depths.items():
            self.map.set_depth(kf_id, depth)
        for kf_id, pose in stored.poses.items():
            self.map.set_pose(kf_id, pose)
        self.map.refresh()
        self._index: tuple[int, int, ScoringIndex] | None = None  # (map revision, basis version, index)
        self._deferred: bool | None = None  # None outside batch(); inside, the metric flag of the last write
        # end of stream: ba's EOS is held until its final graph has been applied (or eos_wait_s passed)
        self.final_keyframes: set[int] | None = None
        self.pending_eos = None
        self.eos_deadline = 0.0
        log.info("map loaded", extra={"stream": cfg.stream, "keyframes": len(stored.contents),
                                      "held": len(self.map.held), "voxels": len(self.map.fused().keys)})

    def close(self) -> None:
        self.store.close()

    # ----- writes ---------------------------------------------------------------------------------
    def add_keyframe(self, kf_id: int, t_ns: int, image: np.ndarray, codes: np.ndarray, intrinsics: np.ndarray,
                     pca_version: int) -> None:
        """Commit then apply a keyframe: image (H, W, 3) uint8 RGB, codes (H/8, W/8, K)."""
        content = KeyframeContent(kf_id, t_ns, codes.astype(np.float16), sample_cell_colours(image),
                                  image.shape[:2], pca_version)
        jpeg = None
        if self.cfg.store_images:
            ok, buf = cv2.imencode(".jpg", cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
            jpeg = buf.tobytes() if ok else None
        with self.lock:
            self.store.put_keyframe(content, intrinsics, jpeg)
            self.intrinsics[kf_id] = np.asarray(intrinsics, np.float64)
            self.map.add_content(content)
            if pca_version not in self.bases:  # zenoh orders per key only: its basis may still be on the way
                log.info("keyframe held until its PCA basis arrives", extra={"stream": self.cfg.stream, "seq": kf_id,
                                                                             "pca_version": pca_version})
            # ba's graph may have overtaken this keyframe on the bus (they come from different services)
            self._refresh(self.metric)

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
            self._refresh(self.metric)
            if self.map.held:
                log.info("keyframes held for their PCA basis", extra={"stream": self.cfg.stream,
                                                                      "held": self.map.held[:10]})

    def update_graph(self, poses: dict[int, np.ndarray], depths: dict[int, KeyframeDepth], metric: bool) -> int:
        """Commit then apply poses and depths; re-fuse what changed. Returns the number of re-fused keyframes."""
        with self.lock:
            self.store.put_graph(poses, depths)
            for kf_id, depth in depths.items():
                self.map.set_depth(kf_id, depth)
            for kf_id, pose in poses.items():
                self.map.set_pose(kf_id, pose)
            return self._refresh(metric)

    @contextmanager
    def batch(self) -> Iterator[None]:
        """Writes inside are committed one by one as always, but re-fused once at the end: a burst of graph
        updates or bases costs one re-fusion of what changed, not one per message."""
        with self.lock:
            self._deferred = self.metric
        try:
            yield
        finally:
            with self.lock:
                metric, self._deferred = self._deferred, None
                self._refresh(metric)

    def _refresh(self, metric: bool) -> int:
        """Re-fuse what changed (lock held); persist the voxel size once known. Returns keyframes re-fused (0
        inside `batch`, which re-fuses at its end)."""
        if self._deferred is not None:
            self._deferred = metric
            return 0
        had_voxel = self.map.voxel_size is not None
        report = self.map.refresh()
        meta = {}
        if not had_voxel and self.map.voxel_size is not None:
            meta["voxel_size"] = repr(float(self.map.voxel_size))
        if metric != self.metric:
            self.metric = metric
            meta["metric"] = "1" if metric else "0"
        if meta:
            self.store.set_meta(meta)
        return len(report.refreshed)

    # ----- reads ----------------------------------------------------------------------------------
    def basis(self) -> PcaBasis:
        if not self.bases:
            raise LookupError("no PCA basis received yet: the map cannot score queries")
        return self.bases[max(self.bases)]

    def index(self) -> ScoringIndex:
        """Scoring index of the current fused map under the latest basis (rebuilt when either changes)."""
        with self.lock:
            basis = self.basis()
            if self._index is None or self._index[:2] != (self.map.revision, basis.version):
                fused = self.map.fused()
                self._index = (self.map.revision, basis.version,
                               ScoringIndex(fused.codes, basis, self.map.params.scoring.device))
            return self._index[2]
