"""One map per session: the database a mapstore opens for a stream belongs to one session of that stream.

A publisher that restarts on a stream opens a new session (services.common.streams). Its map must not be fused
into the previous session's: their world frames are unrelated until something relocalises one against the other.
The stream's database (``db_path``) holds its current session's map and names that session in its ``meta`` table;
when a worker starts for another session, the previous session's database is moved aside whole and unchanged to
``<name>.<session>.db`` beside it (still a complete map database: ``kmvipe map export`` and the query tools open
it), and the new session starts an empty one. A restart within the same session reopens the same database."""
from __future__ import annotations

import glob
import logging
import os
import re
import sqlite3
from contextlib import closing
from pathlib import Path

log = logging.getLogger(__name__)
_NAME = re.compile(r"^[A-Za-z0-9_\-]{1,64}$")  # a stream name (services.common.keys.check_name)
UNNAMED = "unnamed"  # the label of a map written before sessions existed (no session in its meta table)


def recorded_session(path: Path) -> str | None:
    """The session a map database names, "" for a map without one, None when there is no map at ``path``."""
    if not path.is_file():
        return None
    with closing(sqlite3.connect(path)) as conn:
        try:
            row = conn.execute("SELECT value FROM meta WHERE key = 'session'").fetchone()
            empty = conn.execute("SELECT count(*) FROM keyframes").fetchone()[0] == 0
        except sqlite3.OperationalError:  # not a map yet (no tables): nothing to keep
            return None
    if row is None and empty:
        return None
    return row[0] if row is not None else ""


def archive_other_session(path: Path, session: str) -> Path | None:
    """Move the map at ``path`` aside when it belongs to a session other than ``session``; the archive's path,
    or None when there was nothing to move (no map, an empty one, or this session's own)."""
    previous = recorded_session(path)
    if previous is None or previous == session:
        return None
    with closing(sqlite3.connect(path)) as conn:  # fold the write-ahead log in: the moved file is the whole map
        conn.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    archive = path.with_name(f"{path.stem}.{previous or UNNAMED}{path.suffix}")
    os.replace(path, archive)
    for suffix in ("-wal", "-shm"):
        Path(f"{path}{suffix}").unlink(missing_ok=True)
    log.info("a new session starts an empty map; the previous session's map was kept aside", extra={
        "session": session, "previous_session": previous or UNNAMED, "archive": str(archive)})
    return archive


def unfinished(db_path: str) -> list[tuple[str, str]]:
    """(stream, session) of every map under the ``db_path`` template (``{stream}`` in it) whose stream has not
    ended: a mapstore that restarts resumes them, whether or not their source is still there."""
    if "{stream}" not in db_path:
        return []
    prefix, _, suffix = db_path.partition("{stream}")
    found = []
    for name in sorted(glob.glob(glob.escape(prefix) + "*" + glob.escape(suffix))):
        stream, path = name[len(prefix):len(name) - len(suffix)], Path(name)
        if not _NAME.match(stream):  # a moved-aside session's map (<stream>.<session>.db), or a stranger
            continue
        with closing(sqlite3.connect(f"file:{path}?mode=ro", uri=True)) as conn:
            try:
                meta = dict(conn.execute("SELECT key, value FROM meta WHERE key IN ('session', 'finished')"))
            except sqlite3.OperationalError:
                continue
        if meta.get("session") and meta.get("finished") != "1":
            found.append((stream, meta["session"]))
    return found
