"""Which keyframes carve which (see core/map.py's docstring): a keyframe's points are checked against the free
space seen by the next ``carving.later_keyframes`` ready keyframes, each one cached as a carving witness. A mixin of
:class:`services.mapstore.core.map.KeyframeMap`, whose state it works on (``_ready``, ``_views``, ``_unit_codes``,
``_carved``, the keyframe tables); kept apart, as folding is, so the map's fusion reads in one sitting."""
from __future__ import annotations

from bisect import bisect_left

import numpy as np

from services.common.own_pages import own_pages
from services.common.pca_codes import convert_codes
from services.mapstore.core.carving import CarveView, free_space_votes, unit_codes
from services.mapstore.core.keyframe import candidate_points, world_points


class Carving:
    """Carving methods of the keyframe map."""

    def _earlier(self, kf_id: int) -> list[int]:
        """The live ready keyframes before `kf_id` whose points it may carve (folded ones are final)."""
        pos = bisect_left(self._ready, kf_id)
        return [k for k in self._ready[max(0, pos - self.params.carving.later_keyframes) : pos] if k > self.folded_upto]

    def _later(self, kf_id: int) -> list[int]:
        """The ready keyframes after `kf_id` that may carve its points, most recent first."""
        pos = bisect_left(self._ready, kf_id)
        after = pos + 1 if pos < len(self._ready) and self._ready[pos] == kf_id else pos
        return self._ready[after : after + self.params.carving.later_keyframes][::-1]

    def _carve_view(self, kf_id: int) -> CarveView:
        """A keyframe as a carving witness; cached, as each witnesses for up to `later_keyframes` earlier ones."""
        if kf_id not in self._views:
            self._views[kf_id] = self._make_carve_view(kf_id)
        return self._views[kf_id]

    def _make_carve_view(self, kf_id: int) -> CarveView:
        d = self.depths[kf_id]
        reliability = None
        if d.static_weight is not None or d.confidence is not None:
            ones = np.ones(d.disparity.shape, np.float64)
            reliability = ((ones if d.confidence is None else d.confidence)
                           * (ones if d.static_weight is None else d.static_weight))
        codes = self._fused_space_codes(kf_id) if self.params.carving.semantic else None
        return CarveView(np.linalg.inv(self.poses[kf_id]), d.disparity, d.intrinsics, reliability, codes)

    def _fused_space_codes(self, kf_id: int) -> np.ndarray | None:
        """(h, w, K) float32 unit codes of a keyframe in the fused map's code space (cached until its content or
        the code space changes), None without codes; an unversioned map compares codes as they come."""
        if kf_id not in self._unit_codes:
            content = self.contents[kf_id]
            if not content.has_codes:
                self._unit_codes[kf_id] = None
            else:
                cmap = self._code_maps.get(content.pca_version)
                codes = content.codes if cmap is None or cmap.is_identity else convert_codes(content.codes, cmap)
                # kept on pages of its own: ~0.4 MB a keyframe, rebuilt for every live keyframe at each PCA refit
                self._unit_codes[kf_id] = own_pages(unit_codes(codes))
        return self._unit_codes[kf_id]

    def _carved_mask(self, xyz: np.ndarray, cells: np.ndarray, kf_id: int) -> np.ndarray:
        """(C,) bool: which of a keyframe's candidate points (world xyz (C, 3), flat cells (C,)) are carved."""
        views = [self._carve_view(j) for j in self._later(kf_id)]
        codes = None
        own = self._fused_space_codes(kf_id) if self.params.carving.semantic else None
        if own is not None:  # a keyframe without codes is carved on depth evidence alone
            codes = own.reshape(-1, own.shape[2])[cells]
        return free_space_votes(xyz, views, self.params.carving, codes).carved

    def _carving_changed(self, kf_id: int) -> bool:
        """Whether a fused keyframe's carved cells differ now from when it was fused (its own pose/depth unchanged)."""
        cand = candidate_points(self.depths[kf_id], self.params.points)
        xyz = world_points(cand.points_cam, self.poses[kf_id])
        carved = cand.cells[self._carved_mask(xyz, cand.cells, kf_id)]
        return not np.array_equal(carved, self._carved.get(kf_id))
