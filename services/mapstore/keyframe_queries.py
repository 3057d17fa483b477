"""Queryables for query by keyframe region, under ``kmvipe/<s>/map/<verb>`` (dispatched by `queries.answer`).

| verb | request | reply |
|---|---|---|
| keyframes | — | ``KeyframeList``: every stored keyframe (seq, stamp, size, whether it has codes and a thumbnail) |
| keyframe | ``?seq=<n>`` | ``KeyframeThumbnail`` (JPEG), or ``KeyframeRefusal`` not_found |
| example | ``KeyframeQuery`` payload | ``MapAnswer`` as ``map/query`` gives for a text vector, or ``KeyframeRefusal`` |

The query vector of a region is made from the codes the map was built from (`core/pooling.py`), read from the
database (folded keyframes' codes are no longer in memory) and decoded with the basis version they were coded
with; the map then scores it as any backbone-space vector (`queries.query`). A refusal is a reply, not an error
reply, so the gateway can tell an unknown keyframe (404) from one whose codes are not in (409) or a bad box (422).
"""

from __future__ import annotations

import time

import numpy as np

from services.common.schema import (KeyframeList, KeyframeQuery, KeyframeRefusal, KeyframeThumbnail, MapQuery,
                                    Message, decode)
from services.mapstore import queries
from services.mapstore.core.pooling import check_box, region_vector
from services.mapstore.state import MapState

VERBS = ("keyframes", "keyframe", "example")


class Refused(Exception):
    """A request the map cannot answer, with the ``KeyframeRefusal`` status that says why."""

    def __init__(self, status: str, reason: str):
        super().__init__(reason)
        self.status = status


def keyframes(state: MapState, stream: str) -> KeyframeList:
    """Every stored keyframe, folded ones too, ascending seq; ``has_codes`` when its codes and their basis are in."""
    rows = state.store.keyframe_index()
    with state.lock:
        bases = set(state.bases)
    col = lambda i, dtype: np.array([r[i] for r in rows], dtype)  # noqa: E731
    return KeyframeList(stream, len(rows), time.time_ns(), seqs=col(0, np.int64), stamps_ns=col(1, np.int64),
                        widths=col(2, np.int32), heights=col(3, np.int32),
                        has_codes=np.array([r.pca_version in bases for r in rows], np.uint8),
                        has_thumbnail=col(5, np.uint8), session=state.session)


def thumbnail(state: MapState, stream: str, seq: int) -> KeyframeThumbnail:
    thumb = state.store.thumbnail(seq)
    if thumb is None:
        stored = any(r.kf_id == seq for r in state.store.keyframe_index())
        raise Refused("not_found", f"keyframe {seq} has no thumbnail (stored before thumbnails were kept, or "
                                   "KMVIPE_MAPSTORE_THUMBNAIL_SIDE=0)" if stored else f"no keyframe {seq} in this map")
    return KeyframeThumbnail(stream, seq, time.time_ns(), jpeg=thumb.jpeg, width=thumb.width, height=thumb.height,
                             session=state.session)


def region_query(state: MapState, stream: str, q: KeyframeQuery) -> Message:
    """The ``MapAnswer`` of keyframe ``q.keyframe``'s region ``q.box``: its pooled codes as the query vector."""
    try:
        box = check_box(q.box)
    except ValueError as exc:
        raise Refused("bad_request", str(exc)) from exc
    try:
        version, codes = state.store.keyframe_codes(q.keyframe)
    except LookupError as exc:
        raise Refused("not_found", f"no keyframe {q.keyframe} in this map") from exc
    if codes is None:
        raise Refused("no_codes", f"keyframe {q.keyframe} has no DINO codes yet: features sends them after the "
                                  "keyframe's geometry, and a real-time stream may skip them when the backbone lags")
    with state.lock:
        basis = state.bases.get(version)
        if basis is None:
            raise Refused("no_codes", f"keyframe {q.keyframe} was coded with PCA basis version {version}, which "
                                      "has not reached the map yet (it is being fetched from features)")
        vector = region_vector(codes, box, basis.mean, basis.components)
        mq = MapQuery(stream, q.seq, time.time_ns(), vectors=vector[None], space=basis.backbone, top_k=q.top_k,
                      threshold=q.threshold, max_regions=q.max_regions, with_points=q.with_points)
        return queries.query(state, mq)


def answer(state: MapState, stream: str, verb: str, params: dict, payload: bytes | None) -> bytes:
    """One request on ``map/<verb>`` for a verb of `VERBS`; refusals are replies (``KeyframeRefusal``, its ``seq``
    the keyframe asked for, -1 when unknown)."""
    seq = -1
    try:
        if verb == "keyframes":
            return keyframes(state, stream).encode()
        if verb == "keyframe":
            try:
                seq = int(params.get("seq", ""))
            except ValueError as exc:
                raise Refused("bad_request", f"give the keyframe as ?seq=<n>, got {params.get('seq')!r}") from exc
            return thumbnail(state, stream, seq).encode()
        q = decode(payload or b"", KeyframeQuery)
        seq = q.keyframe
        return region_query(state, stream, q).encode()
    except Refused as exc:
        return KeyframeRefusal(stream, seq, time.time_ns(), status=exc.status, reason=str(exc),
                               session=state.session).encode()
