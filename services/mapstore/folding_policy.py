"""When the mapstore folds keyframes (flat memory over an unbounded stream): the policy over ba's graph, the codes
and the stream's kind; what folding does to the map is core/folding.py. A mixin of
:class:`services.mapstore.state.MapState`, whose state it works on (``map``, ``store``, ``cfg``, the graph's keyframes,
``waiting_codes``, ``realtime``, ``folded_exports``); kept apart so the state and this policy each read in one
sitting."""
from __future__ import annotations

import logging

log = logging.getLogger(__name__)


class FoldingPolicy:
    """Which keyframes fold, and what is recorded and exported as they do."""

    def _retired(self, kf_id: int) -> bool:
        """Whether keyframe ``kf_id`` has left ba's graph for good (older than its newest, not in it)."""
        return self._graph_max is not None and kf_id < self._graph_max and kf_id not in self._graph_seqs

    def _settled(self, kf_id: int) -> bool:
        """Nothing will change keyframe ``kf_id`` any more: it has left ba's graph, and its codes are in the map
        (with their basis) or not expected (a real-time stream's); a graph's keyframe that never came counts."""
        if not self._retired(kf_id):
            return False
        content = self.map.contents.get(kf_id)
        if content is None:  # never came (keyframes come in order: later ones are in), codes waiting for it moot
            return True
        if kf_id in self.waiting_codes:  # its codes wait for their basis
            return False
        return content.pca_version in self.bases if content.has_codes else kf_id in self.realtime

    def _fold(self) -> None:
        """Fold the keyframes that can be (lock held, map refreshed): recorded first, then frozen and dropped."""
        if not self.cfg.fold_keyframes or self._graph_max is None:
            return
        ids = self.map.foldable(self._settled)
        forced = False
        if not ids:
            excess = len(self.map.live) - self.cfg.max_live_keyframes
            if excess > 0:
                ids, forced = self.map.foldable(self._retired)[:excess], True
        if not ids:
            return
        modes = [(k, self.map.fold_mode(k)) for k in ids]
        self.store.put_folded(modes)
        self.export_folded(ids)
        self.map.fold(ids)
        for kf_id in ids:
            self.intrinsics.pop(kf_id, None)
            self.realtime.discard(kf_id)
            self.waiting_codes.pop(kf_id, None)
        if forced:
            log.warning("keyframes folded before their codes came (max_live_keyframes reached)",
                        extra={"stream": self.cfg.stream, "seq": ids[-1], "folded": len(ids),
                               "without_codes": sum(m < 2 for _, m in modes)})
        log.debug("keyframes folded", extra={"stream": self.cfg.stream, "seq": ids[-1], "folded": len(ids),
                                             "live": len(self.map.live)})

    def export_folded(self, ids: list[int]) -> None:
        """Depth maps and images of keyframes about to fold into ``export_dir`` (:class:`FoldedExports`)."""
        if self.folded_exports.out is None:
            return
        for kf_id in ids:
            depth, pose = self.map.depths.get(kf_id), self.map.poses.get(kf_id)
            if depth is not None and pose is not None:
                self.folded_exports.write(kf_id, depth, pose, lambda k=kf_id: self.store.image(k), self.metric)
