"""The gateway's side of the mapstore queryables (``kmvipe/<s>/map/{query,segment,export,stats,trajectory}``).

Blocking Zenoh calls; the HTTP layer runs them in a worker thread. A request that finds no queryable at all
answers at once in Zenoh, which is how an unknown stream is told apart from a slow mapstore (a timeout).
"""
from __future__ import annotations

import itertools
import logging
import time
from dataclasses import dataclass

import numpy as np
import zenoh

from ..common import keys
from ..common.bus import Bus
from ..common.errors import DecodeError, KmVipeError, ServiceTimeout, UnknownSession
from ..common.schema import (MapAnswer, MapChunk, MapQuery, MapSegment, MapSessions, MapStats, Message, Poses,
                             decode)

log = logging.getLogger(__name__)
MAPSTORE = "mapstore"
ZENOH_TIMEOUT = "Timeout"  # the error reply Zenoh itself sends when a query times out
UNKNOWN_SESSION = f"{UnknownSession.__name__}:"  # the error reply of a map service for a session it keeps no map of


class StreamNotFound(KmVipeError):
    """No mapstore serves this stream."""

    def __init__(self, stream: str):
        super().__init__(f"unknown stream '{stream}': no mapstore serves {keys.map_key(stream, '**')}")
        self.stream = stream


class MapServiceError(KmVipeError):
    """The mapstore answered with an error, or with a payload that is not the expected message."""


class SessionNotFound(StreamNotFound):
    """The stream's mapstore keeps no map of the session asked for (the message lists the ones it keeps)."""

    def __init__(self, message: str):
        KmVipeError.__init__(self, message)


@dataclass(frozen=True)
class QueryOptions:
    """What to ask the mapstore besides the vectors."""

    top_k: int = 20
    threshold: float = -1.0
    max_regions: int = 10
    with_points: bool = False


class MapClient:
    """Typed requests to the mapstore of any stream over ``bus``; every call may raise StreamNotFound,
    ServiceTimeout (naming the mapstore) or MapServiceError."""

    def __init__(self, bus: Bus, timeout_s: float):
        self.bus, self.timeout_s = bus, timeout_s
        self._request_ids = itertools.count(1)  # thread-safe under the GIL

    def _ask(self, stream: str, verb: str, payload: bytes | None, expect: type[Message], params: str = "",
             session: str = "") -> Message:
        """``session``: an earlier session's map (its archive) instead of the current one."""
        params = ";".join(p for p in (params, f"session={session}" if session else "") if p)
        selector = keys.map_key(stream, verb) + (f"?{params}" if params else "")
        started = time.monotonic()
        errors = []
        for reply in self.bus.session.get(selector, payload=payload, timeout=self.timeout_s):
            if reply.ok is None:
                errors.append(reply.err.payload.to_string())
                continue
            try:
                return decode(reply.ok.payload.to_bytes(), expect)
            except DecodeError as exc:
                raise MapServiceError(f"{MAPSTORE} sent a bad {verb} reply for stream '{stream}': {exc}") from exc
        if errors and any(e != ZENOH_TIMEOUT for e in errors):
            errors = [e for e in errors if e != ZENOH_TIMEOUT]
            if errors[0].startswith(UNKNOWN_SESSION):
                raise SessionNotFound(errors[0][len(UNKNOWN_SESSION):].strip())
            raise MapServiceError(f"{MAPSTORE} of stream '{stream}' refused {verb}: {errors[0]}")
        if not errors and time.monotonic() - started < 0.5 * self.timeout_s:
            raise StreamNotFound(stream)
        raise ServiceTimeout(f"{MAPSTORE} (stream '{stream}', {verb})", self.timeout_s)

    def _query(self, vectors: np.ndarray, space: str, stream: str, opts: QueryOptions) -> bytes:
        msg = MapQuery(stream, next(self._request_ids), time.time_ns(), vectors=np.ascontiguousarray(vectors, np.float32),
                       space=space, top_k=opts.top_k, threshold=opts.threshold, max_regions=opts.max_regions,
                       with_points=opts.with_points)
        return msg.encode()

    def trajectory(self, stream: str, session: str = "") -> Poses:
        """Every frame pose the mapstore has recorded for the stream's current session (or ``session``)."""
        return self._ask(stream, "trajectory", None, Poses, session=session)  # type: ignore[return-value]

    def stats(self, stream: str, session: str = "") -> MapStats:
        return self._ask(stream, "stats", None, MapStats, session=session)  # type: ignore[return-value]

    def sessions(self, stream: str) -> MapSessions:
        """The stream's current session and the earlier ones whose maps the mapstore keeps."""
        return self._ask(stream, "sessions", None, MapSessions)  # type: ignore[return-value]

    def query(self, stream: str, vectors: np.ndarray, space: str, opts: QueryOptions, session: str = "") -> MapAnswer:
        """Regions and top points of (Q, D) float32 ``vectors`` living in backbone space ``space``."""
        return self._ask(stream, "query", self._query(vectors, space, stream, opts), MapAnswer,  # type: ignore
                         session=session)

    def segment(self, stream: str, vectors: np.ndarray, space: str, session: str = "") -> MapSegment:
        """Per-point argmax over the (L, D) label vectors."""
        return self._ask(stream, "segment", self._query(vectors, space, stream, QueryOptions()), MapSegment,  # type: ignore
                         session=session)

    def export_chunk(self, stream: str, index: int, chunk_points: int, session: str = "") -> MapChunk:
        """Chunk ``index`` of the fused map (``n_chunks`` and ``total_points`` say how many follow)."""
        return self._ask(stream, "export", None, MapChunk, f"chunk={index};chunk_size={chunk_points}",  # type: ignore
                         session=session)

    def all_stats(self, timeout_s: float | None = None) -> dict[str, MapStats]:
        """Stats of every stream a mapstore serves (replies to ``kmvipe/*/map/stats``), by stream."""
        found: dict[str, MapStats] = {}
        for reply in self.bus.session.get(keys.map_key("*", "stats"), timeout=timeout_s or self.timeout_s,
                                          consolidation=zenoh.ConsolidationMode.NONE):  # one reply per stream
            if reply.ok is None:
                continue
            try:
                msg = decode(reply.ok.payload.to_bytes(), MapStats)
            except DecodeError as exc:
                log.warning("bad stats reply", extra={"error": str(exc)})
                continue
            found[msg.stream] = msg  # type: ignore[assignment]
        return found
