"""Folding of the keyframe map (flat memory over an unbounded stream; see core/map.py's docstring): settled old
keyframes hand their contribution to frozen sums per PCA version and leave memory. A mixin of
:class:`services.mapstore.core.map.KeyframeMap`, whose state it works on (``_contrib``, ``_frozen``, ``_ready``,
the keyframe tables); kept apart so the map's fusion and its memory bound each read in one sitting."""
from __future__ import annotations

import dataclasses
import logging
from bisect import bisect_right
from typing import Callable

import numpy as np

from services.common.pca_codes import convert_sums
from services.mapstore.core.frozen import FrozenSums
from services.mapstore.core.fusion import RECODE_ROWS, Contribution
from services.mapstore.core.snapping import contains, snap_to_surface

log = logging.getLogger(__name__)


class Folding:
    """Folding methods of the keyframe map."""

    @property
    def fold_window(self) -> int:
        """Later ready keyframes a keyframe's points depend on: the ones that may carve them, and its consistency
        neighbours."""
        return max(self.params.carving.later_keyframes, self.params.consistency.neighbours)

    def is_folded(self, kf_id: int) -> bool:
        """Whether keyframe ``kf_id`` is folded (final; its data is no longer held)."""
        return kf_id <= self.folded_upto

    @property
    def live(self) -> list[int]:
        """Keyframe ids held in memory (anything known that is not folded), ascending."""
        return sorted(k for k in set(self.contents) | set(self.depths) | set(self.poses) if k > self.folded_upto)

    def fold_window_complete(self, kf_id: int) -> bool:
        """Whether the `fold_window` live ready keyframes after ``kf_id`` are all present."""
        live_ready = self._ready[bisect_right(self._ready, self.folded_upto):]
        return len(live_ready) - bisect_right(live_ready, kf_id) >= self.fold_window

    def foldable(self, settled: Callable[[int], bool]) -> list[int]:
        """The oldest live keyframes that can be folded now, ascending: each settled (``settled(kf_id)``: nothing
        upstream will change it — pose, depth, codes), and so is every keyframe up to the last of its
        `fold_window` later ready keyframes. Empty while a refresh is due (fold only up-to-date contributions)."""
        if self._dirty or self._recheck:
            return []
        live = self.live
        unsettled = next((k for k in live if not settled(k)), None)
        live_ready = self._ready[bisect_right(self._ready, self.folded_upto):]
        out = []
        for kf_id in live:
            if unsettled is not None and kf_id >= unsettled:
                break
            last = bisect_right(live_ready, kf_id) + self.fold_window - 1  # its window's last keyframe
            if self.fold_window and (last >= len(live_ready)
                                     or (unsettled is not None and live_ready[last] >= unsettled)):
                break
            out.append(kf_id)
        return out

    def fold_mode(self, kf_id: int) -> int:
        """How a live keyframe would be folded now: 2 its points with codes, 1 its points without codes (geometry
        only), 0 nothing (not fused: no pose, depth or basis)."""
        entry = self._contrib.get(kf_id)
        return 0 if entry is None else 1 if entry[0].codes is None else 2

    def fold(self, ids: list[int]) -> None:
        """Fold every live keyframe up to the newest of ``ids`` (`foldable` gives them in order): their current
        contributions move to the frozen sums of their versions (the fused map does not change, but for voxels that
        join the folded surface along their rays: `_snapped`) and their data leaves memory; a folded ready keyframe
        stays as a ghost (depth and pose) while it is among the `consistency.neighbours` newest folded ones. Raises
        ValueError while a refresh is due."""
        if not ids:
            return
        if self._dirty or self._recheck:
            raise ValueError("refresh before folding: folded contributions must be up to date")
        upto = max(ids)
        for kf_id in [k for k in self.live if k <= upto]:
            entry = self._contrib.pop(kf_id, None)
            if entry is not None:
                contribution = self._snapped(kf_id, *entry)
                version = entry[1] if contribution.codes is not None else None
                self._frozen_sums(version).add(contribution)
                self._frozen_keys = np.union1d(self._frozen_keys, contribution.keys)
            content = self.contents.pop(kf_id, None)
            if content is not None:
                self.folded_count += 1
                # its codes never came; one ba turned into a frame before any graph named it (never fused:
                # no contribution) has its codes all the same
                self.folded_without_codes += not content.has_codes
            for table in (self._carved, self._views, self._unit_codes):
                table.pop(kf_id, None)
        self.folded_upto = max(self.folded_upto, upto)
        self._compact_frozen()
        ready_end = bisect_right(self._ready, self.folded_upto)
        ghosts = set(self._ready[max(0, ready_end - self.params.consistency.neighbours) : ready_end])
        del self._ready[: ready_end - len(ghosts)]
        for table in (self.contents, self.depths, self.poses, self._unit_codes, self._views, self._carved):
            for kf_id in [k for k in table if k <= self.folded_upto and k not in ghosts]:
                del table[kf_id]

    def _snapped(self, kf_id: int, contribution: Contribution, version: int | None) -> Contribution:
        """A folding keyframe's contribution joined to the folded surface along its rays
        (``fusion.fold_snap_voxels``; core/snapping.py), the grid moved with it."""
        reach = self.params.fusion.fold_snap_voxels
        pose = self.poses.get(kf_id)
        if reach <= 0 or pose is None:
            return contribution
        snapped = snap_to_surface(contribution, pose[:3, 3], self._frozen_keys, self.voxel_size, reach)
        if snapped is not contribution:
            self.snapped_voxels += int((~contains(snapped.keys, contribution.keys)).sum())  # moved: key gone
            cmap = self._code_maps.get(version)
            self._grid.apply(contribution, -1, cmap)
            self._grid.apply(snapped, +1, cmap)
            self._fused_cache = None
            self.revision += 1
        return snapped

    def _compact_frozen(self) -> None:
        """Beyond `frozen_versions` versions of frozen sums, convert the oldest into the current version (the grid
        holds them mapped the same way, so the fused map does not change)."""
        versions = sorted(v for v in self._frozen if v is not None and v != self.code_version)
        if self.code_version is None:
            return
        while len(versions) + (self.code_version in self._frozen) > self.frozen_versions and versions:
            old = versions.pop(0)
            sums, cmap, into = self._frozen.pop(old), self._code_maps[old], self._frozen_sums(self.code_version)
            for part in sums:  # a chunk at a time; each converted in float64 a few rows at a time
                codes = np.empty((part.keys.size, cmap.matrix.shape[0]), np.float32)
                for start in range(0, part.keys.size, RECODE_ROWS):
                    rows = slice(start, start + RECODE_ROWS)
                    codes[rows] = convert_sums(part.codes[rows], part.weight[rows], cmap)
                into.add(dataclasses.replace(part, codes=codes))
            sums.discard()
            log.info("frozen sums of PCA version %d carried in version %d", old, self.code_version)

    def _frozen_sums(self, version: int | None) -> FrozenSums:
        """The frozen sums of one PCA version (None: of keyframes without codes), made on first use."""
        if version not in self._frozen:
            self._frozen[version] = FrozenSums(self.frozen_store)
        return self._frozen[version]

    @property
    def frozen_voxels(self) -> int:
        """Voxel rows held by the frozen sums (all versions)."""
        return sum(len(f) for f in self._frozen.values())
