"""Earlier sessions' maps, queryable: a session that ended stays a map of its own.

A new session of a stream moves the previous session's database aside whole (``<name>.<session>.db`` beside the
stream's map; services/mapstore/sessions.py). Every map verb takes ``?session=<id>``: the current session is
served by the live state, an earlier one by a :class:`MapState` opened on its archived database on demand (the
few most recent kept open). Nothing is written to an archive: its stream ended, and nothing of its session is
fused any more. ``map/sessions`` lists them."""
from __future__ import annotations

import sqlite3
import threading
from collections import OrderedDict
from contextlib import closing
from pathlib import Path

import numpy as np

from ..common.errors import UnknownSession
from ..common.schema import MapSessions
from ..common.wire_check import SESSION_NAME
from . import queries
from .config import MapstoreSettings
from .state import MapState



def _meta(path: Path) -> tuple[str, int, bool] | None:
    """(session, keyframes, finished) of the map database at ``path``; None when it is not one."""
    try:
        with closing(sqlite3.connect(f"file:{path}?mode=ro", uri=True)) as conn:
            meta = dict(conn.execute("SELECT key, value FROM meta WHERE key IN ('session', 'finished')"))
            count = conn.execute("SELECT count(*) FROM keyframes").fetchone()[0]
    except sqlite3.Error:
        return None
    return meta.get("session", ""), int(count), meta.get("finished") == "1"


class ArchivedMaps:
    """The archived session maps of one stream's database path (thread-safe; queryables run on Zenoh threads)."""

    def __init__(self, cfg: MapstoreSettings, keep_open: int = 2) -> None:
        self.cfg, self.keep_open = cfg, keep_open
        self.path = Path(cfg.db_path.format(stream=cfg.stream))
        self._open: OrderedDict[str, MapState] = OrderedDict()
        self._lock = threading.Lock()

    def path_of(self, session: str) -> Path:
        return self.path.with_name(f"{self.path.stem}.{session}{self.path.suffix}")

    def archived(self) -> list[tuple[str, int, bool]]:
        """(session, keyframes, finished) of every archived map of the stream, oldest session first."""
        found = []
        for candidate in sorted(self.path.parent.glob(f"{self.path.stem}.*{self.path.suffix}")):
            session = candidate.name[len(self.path.stem) + 1:len(candidate.name) - len(self.path.suffix)]
            meta = _meta(candidate) if SESSION_NAME.match(session) else None
            if meta is not None:
                found.append((session, meta[1], meta[2]))
        return found

    def listing(self, current: MapState, stream: str) -> MapSessions:
        """The current session (first) and every archived one."""
        live = _meta(self.path)
        rows = [(current.session, current.keyframe_count(), bool(live and live[2]))]
        rows += [r for r in self.archived() if r[0] != current.session]
        return MapSessions(stream, 0, 0, current=current.session, names="\n".join(r[0] for r in rows),
                           keyframes=np.array([r[1] for r in rows], np.int64),
                           finished=np.array([r[2] for r in rows], np.uint8))

    def pick(self, current: MapState, params: dict) -> MapState:
        """The state that serves a request: the live one, or the archived map ``params['session']`` names."""
        session = params.get("session", "")
        if not session or session == current.session:
            return current
        if not SESSION_NAME.match(session) or not self.path_of(session).is_file():
            known = [current.session] + [r[0] for r in self.archived()]
            raise UnknownSession(f"stream {self.cfg.stream!r} has no map of session {session!r}; sessions: "
                                 f"{', '.join(s for s in known if s) or 'none'}")
        with self._lock:
            state = self._open.get(session)
            if state is None:
                cfg = self.cfg.model_copy(update={"db_path": str(self.path_of(session))})
                state = self._open[session] = MapState(cfg)  # no session given: nothing is moved or renamed
                while len(self._open) > self.keep_open:
                    evicted = self._open.popitem(last=False)[1]
                    with evicted.lock:  # after the queries it is answering
                        evicted.close()
            self._open.move_to_end(session)
            return state

    def answer(self, current: MapState, stream: str, key: str, params: dict, payload: bytes | None) -> bytes:
        """The map queryable's handler: ``map/sessions`` here, every other verb by the session's state."""
        if key.rsplit("/", 1)[-1] == "sessions":
            return self.listing(current, stream).encode()
        return queries.answer(self.pick(current, params), stream, key, params, payload)

    def close(self) -> None:
        with self._lock:
            for state in self._open.values():
                state.close()
            self._open.clear()
