"""The keyframe-anchored map: keyframes (codes, colours, depth, pose) and their voxel fusion.

Keyframes whose pose or depth changed — and their consistency neighbours, whose check depends on them — are
marked dirty; `refresh()` re-fuses exactly those by subtracting their old contribution and adding the new one.
The earlier keyframes a changed keyframe may carve (core/carving.py; which carve which: core/carving_views.py)
are re-checked first: only those whose carved cells changed are re-fused.

Codes stay in the PCA version each keyframe was coded with; the fused map is in one version, `code_version`
(the latest basis), reached from each keyframe's own version by one affine map (`set_code_space`). A keyframe
whose version has no map yet is held like one without depth or pose: kept, not fused, fused once it has one.

A keyframe without codes (features sends a keyframe's geometry at once and its codes later) is fused for
geometry at once: points, colours and depth evidence for carving, no code sums (code weight 0), no semantic
carving evidence either way. `set_codes` gives it its codes later and re-fuses just it (its neighbours' depth
consistency does not depend on codes; the earlier keyframes it may carve are re-checked).

Folding (flat memory over an unbounded stream; core/folding.py): a keyframe is *settled* when nothing upstream will change it
again (the caller decides: it has left ba's graph and its codes are in or not expected). The oldest keyframes
whose `fold_window` later ready keyframes — the ones that may carve them, and their consistency neighbours — are
settled too can no longer change at all: `fold` hands their contribution to a frozen accumulator per PCA version
(`FrozenSums`, sized by the map's voxels, not by the stream) and drops their codes, colours, depth and carving
state. Folding goes in id order, so the live keyframes are always the newest ones; the last
`consistency.neighbours` folded ready keyframes keep their depth and pose (ghosts) as consistency neighbours of the
oldest live ones. The fused map is the same as without folding, except that folded points are final: a new PCA
basis converts their code sums exactly but no longer re-judges their semantic carving, and codes or graph updates
for a folded keyframe are ignored (the caller keeps them out); and, with ``fusion.fold_snap_voxels``, a folding
keyframe's voxels that no folded voxel holds join the folded surface along their lines of sight (core/snapping.py),
so revisits do not thicken it. Frozen sums are kept per PCA version for the newest
`frozen_versions` versions; an older version's sums are converted into the current version and merged there
(exact now; a later basis then reaches them through one more projection), so many refits cannot multiply them.
"""

from __future__ import annotations

import logging
from bisect import bisect_left
from typing import Iterable, NamedTuple

import numpy as np

from services.common.pca_codes import CodeMap, code_map, identity_map
from services.mapstore.config import MapParams
from services.mapstore.core.carving import CarveView
from services.mapstore.core.consistency import NeighbourView, depth_consistency
from services.mapstore.core.carving_views import Carving
from services.mapstore.core.folding import Folding
from services.mapstore.core.frozen import FrozenSums, SumsStore
from services.mapstore.core.fusion import Contribution, FusedVoxels, VoxelGrid, make_contribution
from services.mapstore.core.keyframe import KeyframeContent, KeyframeDepth, candidate_points, world_points
from services.mapstore.core.scoring import PcaBasis

log = logging.getLogger(__name__)


class KeyframePoints(NamedTuple):
    """The points one keyframe contributes to the map (M points)."""

    cells: np.ndarray  # (M,) int64 flat grid cell index r·w + c
    xyz: np.ndarray  # (M, 3) float64 world coordinates under the keyframe's latest pose
    weight: np.ndarray  # (M,) float64 confidence × static × consistency (carved points are left out)
    codes: np.ndarray | None  # (M, K) float16 in the keyframe's own PCA version (content.pca_version); None: no codes
    colours: np.ndarray  # (M, 3) uint8


class RefreshReport(NamedTuple):
    """What one `refresh()` did."""

    refreshed: list[int]  # keyframe ids re-fused
    voxels: int  # occupied voxels afterwards


def code_maps_to_latest(bases: dict[int, PcaBasis]) -> tuple[int, dict[int, CodeMap]]:
    """(latest version, {version: map from its codes to the latest's}) for every known basis (at least one)."""
    if not bases:
        raise ValueError("no PCA basis known")
    latest = max(bases)
    return latest, {v: identity_map(b.rank) if v == latest else code_map(b, bases[latest]) for v, b in bases.items()}


class KeyframeMap(Carving, Folding):
    """Mutable map state; no I/O. Feed it keyframe content, depths and poses, then `refresh()`."""

    def __init__(self, params: MapParams, voxel_size: float | None = None, versioned: bool = False,
                 frozen_versions: int = 8, frozen_store: SumsStore | None = None) -> None:
        """
        Args:
            params: the map parameters.
            voxel_size: fixed voxel edge in world units; None derives it from params.fusion
                (absolute, or relative to the median depth of the first fused keyframe).
            versioned: hold every keyframe until `set_code_space` gives a map for its PCA version; False fuses
                codes as they come (for callers whose keyframes share one version).
            frozen_versions: PCA versions whose folded sums are kept apart (older ones merge into the current).
            frozen_store: where the folded sums' merged rows are kept (core/frozen.py); None: in memory.
        """
        self.frozen_versions = frozen_versions
        self.frozen_store = frozen_store
        self.versioned = versioned
        self.params = params
        self.contents: dict[int, KeyframeContent] = {}
        self.depths: dict[int, KeyframeDepth] = {}
        self.poses: dict[int, np.ndarray] = {}
        self.voxel_size = voxel_size
        if voxel_size is None and params.fusion.voxel_mode == "absolute":
            self.voxel_size = params.fusion.voxel_size
        self._grid: VoxelGrid | None = None
        self._contrib: dict[int, tuple[Contribution, int | None]] = {}  # per fused keyframe: (sums, their PCA
        # version; None for a keyframe without codes)
        self.code_version: int | None = None  # PCA version of the fused codes; None until a basis is known
        self._code_maps: dict[int, CodeMap] = {}  # PCA version -> map of its codes into code_version
        self._dirty: set[int] = set()
        self._recheck: set[int] = set()  # keyframes whose carving may have changed
        self._carved: dict[int, np.ndarray] = {}  # per fused keyframe: (C,) int64 cells carved when it was fused
        self._unit_codes: dict[int, np.ndarray | None] = {}  # per keyframe: (h, w, K) unit codes in code_version
        # (carving); None for a keyframe without codes
        self._views: dict[int, CarveView] = {}  # per keyframe: itself as a carving witness (until it is touched)
        self._ready: list[int] = []  # sorted ids with content, depth and pose
        self._fused_cache: FusedVoxels | None = None
        self.revision = 0
        self._frozen: dict[int | None, FrozenSums] = {}  # folded keyframes' sums per PCA version (None: no codes)
        self._frozen_keys = np.zeros(0, np.int64)  # ascending keys of every voxel the frozen sums hold
        self.snapped_voxels = 0  # folded keyframes' voxels moved onto the folded surface (fusion.fold_snap_voxels)
        self.folded_upto = -1  # the newest folded keyframe id: every keyframe at or below it is folded
        self.folded_count = 0  # keyframes folded (with content)
        self.folded_without_codes = 0  # of those, folded before their codes came (geometry only, or nothing)

    # ----- inputs -------------------------------------------------------------------------
    def add_content(self, content: KeyframeContent) -> None:
        """Add or replace a keyframe's codes (None: not yet in) and colours (ignored for a folded keyframe)."""
        if self.is_folded(content.kf_id):
            return
        self.contents[content.kf_id] = content
        self._unit_codes.pop(content.kf_id, None)
        self._touch(content.kf_id)

    def set_codes(self, kf_id: int, codes: np.ndarray, pca_version: int) -> None:
        """Give a keyframe (content already added, e.g. without codes) its (h, w, K) codes in ``pca_version``.

        Only the keyframe itself is re-fused (its points' code sums and its own semantic carving) and the earlier
        keyframes it witnesses for are re-checked; its neighbours' depth consistency does not depend on codes.
        Ignored for a folded keyframe."""
        if self.is_folded(kf_id):
            return
        old = self.contents[kf_id]
        content = KeyframeContent(kf_id, old.t_ns, codes, old.colours, old.image_hw, pca_version)
        was_ready = self._is_ready(kf_id)
        self.contents[kf_id] = content
        self._unit_codes.pop(kf_id, None)
        if self._is_ready(kf_id) != was_ready:  # e.g. codes of a version with no map yet: held, neighbours change
            self._touch(kf_id)
            return
        self._views.pop(kf_id, None)
        self._dirty.add(kf_id)
        if self.params.carving.semantic:
            self._recheck.update(self._earlier(kf_id))

    @property
    def without_codes(self) -> list[int]:
        """Keyframes whose codes have not arrived (fused for geometry only), ascending."""
        return sorted(k for k, c in self.contents.items() if not c.has_codes)

    def set_depth(self, kf_id: int, depth: KeyframeDepth) -> None:
        """Set a keyframe's latest disparity/weights (its grid must match its codes' grid); ignored once folded, and
        a no-op when unchanged (ba's final graph resends every held keyframe's maps; re-fusing the ~70 % its BA did
        not move was most of the end of stream's re-fusion)."""
        if self.is_folded(kf_id) or depth.same_as(self.depths.get(kf_id)):
            return
        self.depths[kf_id] = depth
        self._touch(kf_id)

    def set_pose(self, kf_id: int, world_from_cam: np.ndarray) -> None:
        """Set a keyframe's latest (4, 4) float64 world_from_cam; an unchanged pose (or a folded keyframe's) is a
        no-op."""
        pose = np.asarray(world_from_cam, dtype=np.float64)
        if pose.shape != (4, 4):
            raise ValueError(f"world_from_cam must be (4, 4), got {pose.shape}")
        if self.is_folded(kf_id):
            return
        old = self.poses.get(kf_id)
        if old is not None and np.array_equal(old, pose):
            return
        self.poses[kf_id] = pose.copy()
        self._touch(kf_id)

    def remove(self, kf_id: int) -> None:
        """Forget a keyframe and take its points out of the map at the next refresh (a folded one stays)."""
        if self.is_folded(kf_id):
            return
        for table in (self.contents, self.depths, self.poses, self._unit_codes):
            table.pop(kf_id, None)
        self._touch(kf_id)

    def _is_ready(self, kf_id: int) -> bool:
        c, d = self.contents.get(kf_id), self.depths.get(kf_id)
        return (c is not None and d is not None and kf_id in self.poses and c.grid_shape == d.disparity.shape
                and (not self.versioned or not c.has_codes or c.pca_version in self._code_maps))

    def set_code_space(self, version: int, maps: dict[int, CodeMap]) -> None:
        """Put the fused map's codes into PCA version ``version``; ``maps[v]`` maps version v's (…, K_v) codes into
        it (identity for ``version`` itself) and must cover every fused keyframe's version. Fused code sums are
        re-summed through the new maps (no geometry is recomputed); held keyframes whose version now has a map
        are fused at the next `refresh`."""
        if version not in maps:
            raise ValueError(f"code maps must include the target version {version}")
        if not self.versioned:
            raise ValueError("set_code_space needs a map built with versioned=True")
        missing = ({v for _, v in self._contrib.values()} | set(self._frozen)) - {None} - set(maps)
        if missing:
            raise ValueError(f"no code map for fused versions {sorted(missing)}")
        held = [k for k in self.contents if not self._is_ready(k)]
        if version != self.code_version and self.params.carving.semantic:
            self._recheck.update(self._carved)  # carving compares codes in the fused space, which changes
        self.code_version, self._code_maps = version, dict(maps)
        self._unit_codes.clear()
        self._views.clear()
        if self._grid is not None:
            self._grid.recode([(chunks, self._code_maps[v]) for chunks, v in self._parts() if v is not None],
                              maps[version].matrix.shape[0])
        for kf_id in held:
            if self._is_ready(kf_id):
                self._touch(kf_id)
        self.revision += 1
        self._fused_cache = None

    @property
    def held(self) -> list[int]:
        """Keyframes with codes whose PCA version has no code map yet (kept, not fused), ascending."""
        return sorted(k for k, c in self.contents.items()
                      if self.versioned and c.has_codes and c.pca_version not in self._code_maps)

    def _touch(self, kf_id: int) -> None:
        """Mark a keyframe and its consistency neighbours dirty; keep the ready list sorted."""
        pos = bisect_left(self._ready, kf_id)
        present = pos < len(self._ready) and self._ready[pos] == kf_id
        if self._is_ready(kf_id) and not present:
            self._ready.insert(pos, kf_id)
        elif not self._is_ready(kf_id) and present:
            self._ready.pop(pos)
        self._views.pop(kf_id, None)
        self._dirty.add(kf_id)
        self._dirty.update(k for k in self._neighbours(kf_id) if k > self.folded_upto)  # not the ghosts
        self._recheck.update(self._earlier(kf_id))

    def _neighbours(self, kf_id: int) -> list[int]:
        n = self.params.consistency.neighbours
        pos = bisect_left(self._ready, kf_id)
        after = pos + 1 if pos < len(self._ready) and self._ready[pos] == kf_id else pos
        return self._ready[max(0, pos - n) : pos] + self._ready[after : after + n]

    # ----- fusion -------------------------------------------------------------------------
    @property
    def dirty(self) -> set[int]:
        """Keyframe ids waiting to be re-fused."""
        return set(self._dirty)

    def keyframe_points(self, kf_id: int) -> KeyframePoints:
        """The points keyframe `kf_id` contributes under its latest pose, depth, neighbours and later keyframes."""
        return self._points(kf_id)[0]

    def _points(self, kf_id: int) -> tuple[KeyframePoints, np.ndarray]:
        """(the keyframe's points, (C,) int64 its candidate cells carved as free space)."""
        content, depth = self.contents[kf_id], self.depths[kf_id]
        cand = candidate_points(depth, self.params.points)
        xyz = world_points(cand.points_cam, self.poses[kf_id])
        views = [NeighbourView(np.linalg.inv(self.poses[j]), self.depths[j].disparity, self.depths[j].intrinsics)
                 for j in self._neighbours(kf_id)]
        weight = cand.base_weight * depth_consistency(xyz, views, self.params.consistency)
        carved = self._carved_mask(xyz, cand.cells, kf_id)
        keep = (weight >= self.params.points.min_weight) & ~carved
        cells = cand.cells[keep]
        codes = None if content.codes is None else content.codes.reshape(-1, content.codes.shape[2])[cells]
        points = KeyframePoints(cells, xyz[keep], weight[keep], codes, content.colours.reshape(-1, 3)[cells])
        return points, cand.cells[carved]

    def _ensure_voxel_size(self, first_kf: int) -> None:
        if self.voxel_size is not None:
            return
        cand = candidate_points(self.depths[first_kf], self.params.points)
        median = float(np.median(cand.points_cam[:, 2])) if len(cand.cells) else 1.0
        self.voxel_size = self.params.fusion.voxel_size * median
        log.info("voxel size %.4g = %.3g x median depth %.4g of keyframe %d",
                 self.voxel_size, self.params.fusion.voxel_size, median, first_kf)

    def refresh(self) -> RefreshReport:
        """Re-fuse every dirty keyframe (subtract its old contribution, add the new one)."""
        recheck = {k for k in self._recheck - self._dirty if k > self.folded_upto}
        self._dirty.update(k for k in recheck if k not in self._carved or self._carving_changed(k))
        self._recheck.clear()
        dirty = sorted(k for k in self._dirty if k > self.folded_upto)
        self._dirty.clear()
        for kf_id in dirty:
            old = self._contrib.pop(kf_id, None)
            self._carved.pop(kf_id, None)
            if old is not None:
                self._grid.apply(old[0], -1, self._code_maps.get(old[1]))
            if not self._is_ready(kf_id):
                continue
            self._ensure_voxel_size(kf_id)
            pts, self._carved[kf_id] = self._points(kf_id)
            version = self.contents[kf_id].pca_version if pts.codes is not None else None
            cmap = self._code_maps.get(version)  # None: unversioned map (codes as they are), or no codes
            if self._grid is None:
                self._grid = VoxelGrid(self._code_dim(pts.codes, cmap))
            contribution = make_contribution(pts.xyz, pts.weight, pts.codes, pts.colours, self.voxel_size)
            contribution = contribution.on_own_pages()  # kept until the next re-fusion: off the heap
            self._grid.apply(contribution, +1, cmap)
            self._contrib[kf_id] = (contribution, version)
        if dirty:
            self.revision += 1
            self._fused_cache = None
        if self._grid is not None:
            self._grid.compact()  # after voxels emptied (carving, a keyframe moved): memory follows the map
        return RefreshReport(dirty, len(self._grid) if self._grid is not None else 0)

    def _code_dim(self, codes: np.ndarray | None, cmap) -> int:
        """K of the fused codes: the current version's, else the codes' own, else any content's (0: none known
        yet; the grid takes it from the first codes it is given)."""
        if cmap is not None:
            return cmap.matrix.shape[0]
        if self.code_version is not None:
            return self._code_maps[self.code_version].matrix.shape[0]
        if codes is not None:
            return codes.shape[1]
        return next((c.codes.shape[2] for c in self.contents.values() if c.has_codes), 0)

    def fused(self) -> FusedVoxels:
        """The fused map (one point per occupied voxel), cached until the next change."""
        if self._fused_cache is None:
            if self._grid is None:
                self._fused_cache = VoxelGrid(self._code_dim(None, None), 1).fused()
            else:
                self._fused_cache = self._grid.fused()
        return self._fused_cache

    def rebuild(self, voxel_size: float | None = None) -> RefreshReport:
        """Drop all fusion state and re-fuse every live keyframe (e.g. after a scale change). Folded keyframes'
        sums are kept as they are, so with any folded the voxel size cannot change (None keeps it)."""
        if self._frozen:
            if voxel_size is not None and voxel_size != self.voxel_size:
                raise ValueError("folded keyframes are fused at their voxel size; it cannot change")
            voxel_size = self.voxel_size
        self.voxel_size = voxel_size
        if voxel_size is None and self.params.fusion.voxel_mode == "absolute":
            self.voxel_size = self.params.fusion.voxel_size
        self._grid, self._contrib, self._carved, self._recheck = None, {}, {}, set()
        for version, part in self._frozen.items():
            cmap = self._code_maps.get(version)
            if self._grid is None:
                self._grid = VoxelGrid(self._code_dim(None, cmap))
            for chunk in part:
                self._grid.apply(chunk, +1, cmap)
        self._dirty = {k for k in set(self.contents) | set(self.depths) | set(self.poses) if k > self.folded_upto}
        self.revision += 1
        self._fused_cache = None
        return self.refresh()

    # ----- folding ------------------------------------------------------------------------
    def _parts(self) -> list[tuple[Iterable[Contribution], int | None]]:
        """Every contribution in the grid with its PCA version, as iterables of contributions: each live
        keyframe's (one), and the frozen sums of each version (in chunks)."""
        return [([c], v) for c, v in self._contrib.values()] + [(f, v) for v, f in self._frozen.items()]
