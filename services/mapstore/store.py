"""Durable map store: SQLite in WAL mode, one row per keyframe, arrays as .npy blobs (`blobs.py`).

Why SQLite/WAL: one file, atomic multi-row transactions (a graph update of many poses and depths
commits all or nothing), readers never block the writer, and a killed process loses nothing that was
committed. A keyframe is acknowledged (and applied to the in-memory map) only after its transaction
commits, so what queries see is always a subset of what a restart reloads.

Folded keyframes (``core/map.py``: final, their sums frozen, their arrays no longer in memory) stay here; the
``folded`` table records how each was folded (with codes, geometry only, or not at all), so a restart rebuilds
the same frozen sums. `iter_keyframes` reads the keyframes page by page in id order: a restart, an export and
`kmvipe map export` never hold every keyframe at once.
"""

from __future__ import annotations

import logging
import sqlite3
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, Literal, NamedTuple

import numpy as np

from services.mapstore.blobs import from_blob, to_blob
from services.mapstore.core.keyframe import KeyframeContent, KeyframeDepth
from services.mapstore.core.scoring import PcaBasis

log = logging.getLogger(__name__)

MIGRATIONS: list[str] = [
    # 1: keyframes, their latest geometry and pose, PCA bases, free-form metadata
    """
    CREATE TABLE keyframes (kf_id INTEGER PRIMARY KEY, t_ns INTEGER NOT NULL, pca_version INTEGER NOT NULL,
        height INTEGER NOT NULL, width INTEGER NOT NULL, codes BLOB NOT NULL, colours BLOB NOT NULL);
    CREATE TABLE depths (kf_id INTEGER PRIMARY KEY, intrinsics BLOB NOT NULL, disparity BLOB NOT NULL,
        static_weight BLOB, confidence BLOB, revision INTEGER NOT NULL DEFAULT 0);
    CREATE TABLE poses (kf_id INTEGER PRIMARY KEY, world_from_cam BLOB NOT NULL, revision INTEGER NOT NULL DEFAULT 0);
    CREATE TABLE pca (version INTEGER PRIMARY KEY, backbone TEXT NOT NULL, mean BLOB NOT NULL,
        components BLOB NOT NULL);
    CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
    """,
    # 2: working-resolution images (JPEG) for exports, and the camera intrinsics the keyframe came with
    """
    CREATE TABLE images (kf_id INTEGER PRIMARY KEY, jpeg BLOB NOT NULL);
    ALTER TABLE keyframes ADD COLUMN intrinsics BLOB;
    """,
    # 3: a keyframe's codes follow its geometry (NULL until they arrive, pca_version -1), and whether it came from
    # a real-time stream (whose keyframes may never get codes). SQLite cannot drop a NOT NULL: copy the table.
    """
    CREATE TABLE keyframes_v3 (kf_id INTEGER PRIMARY KEY, t_ns INTEGER NOT NULL, pca_version INTEGER NOT NULL,
        height INTEGER NOT NULL, width INTEGER NOT NULL, codes BLOB, colours BLOB NOT NULL, intrinsics BLOB,
        realtime INTEGER NOT NULL DEFAULT 0);
    INSERT INTO keyframes_v3 (kf_id, t_ns, pca_version, height, width, codes, colours, intrinsics)
        SELECT kf_id, t_ns, pca_version, height, width, codes, colours, intrinsics FROM keyframes;
    DROP TABLE keyframes;
    ALTER TABLE keyframes_v3 RENAME TO keyframes;
    """,
    # 4: folded keyframes (flat memory): mode 2 = folded with its codes, 1 = geometry only (codes that came later
    # stay out of the map), 0 = folded with no contribution (it had no pose, depth or basis)
    """
    CREATE TABLE folded (kf_id INTEGER PRIMARY KEY, mode INTEGER NOT NULL);
    """,
    # 5: every frame's latest pose (the trajectory ba publishes; mapping's revisions win over tracking's poses),
    # so the trajectory outlives a restarted gateway; 16 little-endian float64 each (a whole stream is read at once)
    """
    CREATE TABLE frame_poses (seq INTEGER PRIMARY KEY, t_ns INTEGER NOT NULL, world_from_cam BLOB NOT NULL,
        mapped INTEGER NOT NULL DEFAULT 0);
    """,
    # 6: a small JPEG per keyframe (longest side ``thumbnail_side``): the viewer's keyframe strip, query by region
    """
    CREATE TABLE thumbnails (kf_id INTEGER PRIMARY KEY, width INTEGER NOT NULL, height INTEGER NOT NULL,
        jpeg BLOB NOT NULL);
    """,
]
SCHEMA_VERSION = len(MIGRATIONS)


def schema_version(conn: sqlite3.Connection) -> int:
    """The schema version of an open database (0 for an empty one)."""
    conn.execute("CREATE TABLE IF NOT EXISTS schema_version (version INTEGER NOT NULL)")
    row = conn.execute("SELECT MAX(version) FROM schema_version").fetchone()
    return int(row[0] or 0)


def migrate(conn: sqlite3.Connection, target: int = SCHEMA_VERSION) -> int:
    """Apply the missing migrations up to `target`, each in its own transaction; returns the version."""
    current = schema_version(conn)
    if current > SCHEMA_VERSION:
        raise RuntimeError(f"map database has schema {current}, newer than this code ({SCHEMA_VERSION})")
    for version in range(current + 1, target + 1):
        with conn:
            conn.execute("BEGIN")
            for statement in MIGRATIONS[version - 1].split(";"):
                if statement.strip():
                    conn.execute(statement)
            conn.execute("INSERT INTO schema_version (version) VALUES (?)", (version,))
        log.info("map database migrated to schema %d", version)
    return max(current, target)


@dataclass
class StoredMap:
    """Everything a restart reloads."""

    contents: dict[int, KeyframeContent] = field(default_factory=dict)  # codes None: not arrived yet
    realtime: set[int] = field(default_factory=set)  # keyframes of a real-time stream (codes may never come)
    intrinsics: dict[int, np.ndarray] = field(default_factory=dict)  # as the keyframe arrived, (4,) float64
    depths: dict[int, KeyframeDepth] = field(default_factory=dict)
    poses: dict[int, np.ndarray] = field(default_factory=dict)  # (4, 4) float64 world_from_cam
    bases: dict[int, PcaBasis] = field(default_factory=dict)
    meta: dict[str, str] = field(default_factory=dict)


class StoredKeyframe(NamedTuple):
    """One keyframe id's rows (any may be missing: a graph can name a keyframe that never came)."""

    kf_id: int
    content: KeyframeContent | None  # codes None: not arrived yet (or not read: ``iter_keyframes(codes=False)``)
    depth: KeyframeDepth | None
    pose: np.ndarray | None  # (4, 4) float64 world_from_cam
    intrinsics: np.ndarray | None  # (4,) float64 as the keyframe arrived
    realtime: bool
    folded: int | None  # None: live; else the fold mode (2 with codes, 1 geometry only, 0 nothing)


class KeyframeRow(NamedTuple):
    """One row of `MapStore.keyframe_index`."""

    kf_id: int
    t_ns: int
    width: int  # working image, pixels
    height: int
    pca_version: int  # of its codes; -1: no codes stored
    has_thumbnail: bool


class Thumbnail(NamedTuple):
    jpeg: bytes
    width: int
    height: int


class MapStore:
    """The map database. Every `put_*` is one transaction: when it returns, the data is durable."""

    def __init__(self, path: Path | str, synchronous: Literal["NORMAL", "FULL"] = "FULL") -> None:
        """
        Args:
            path: SQLite file (created with its folder when missing).
            synchronous: FULL also survives power loss; NORMAL (WAL) survives a killed process.
        """
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        # isolation_level=None: we issue BEGIN ourselves, so a transaction is exactly one put_*
        self._conn = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False)
        self._lock = threading.Lock()
        self._conn.execute("PRAGMA journal_mode=WAL")
        self._conn.execute(f"PRAGMA synchronous={synchronous}")
        migrate(self._conn)

    def close(self) -> None:
        self._conn.close()

    def __enter__(self) -> MapStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _write(self, statements: list[tuple[str, tuple]]) -> int:
        """Run the statements in one transaction; returns the rows they changed."""
        changed = 0
        with self._lock:
            self._conn.execute("BEGIN IMMEDIATE")
            try:
                for sql, args in statements:
                    changed += max(self._conn.execute(sql, args).rowcount, 0)
            except BaseException:
                self._conn.execute("ROLLBACK")
                raise
            self._conn.execute("COMMIT")
        return changed

    def put_keyframe(self, content: KeyframeContent, intrinsics: np.ndarray, jpeg: bytes | None = None,
                     realtime: bool = False, thumbnail: Thumbnail | None = None) -> None:
        """Store a keyframe's codes (or none yet), colours, arrival intrinsics (4,), optional JPEG image and
        thumbnail, and whether it came from a real-time stream."""
        h, w = content.image_hw
        rows = [("INSERT OR REPLACE INTO keyframes (kf_id, t_ns, pca_version, height, width, codes, colours, "
                 "intrinsics, realtime) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
                 (content.kf_id, content.t_ns, content.pca_version, h, w, to_blob(content.codes),
                  to_blob(content.colours), to_blob(np.asarray(intrinsics, np.float64)), int(realtime)))]
        if jpeg is not None:
            rows.append(("INSERT OR REPLACE INTO images (kf_id, jpeg) VALUES (?, ?)", (content.kf_id, jpeg)))
        if thumbnail is not None:
            rows.append(("INSERT OR REPLACE INTO thumbnails (kf_id, width, height, jpeg) VALUES (?, ?, ?, ?)",
                         (content.kf_id, thumbnail.width, thumbnail.height, thumbnail.jpeg)))
        self._write(rows)

    def put_codes(self, kf_id: int, pca_version: int, codes: np.ndarray) -> None:
        """Store the codes (h, w, K) of a stored keyframe, coded with basis ``pca_version`` (they follow its
        geometry); LookupError if the keyframe is not stored."""
        if not self._write([("UPDATE keyframes SET codes = ?, pca_version = ? WHERE kf_id = ?",
                             (to_blob(codes), int(pca_version), int(kf_id)))]):
            raise LookupError(f"codes for keyframe {kf_id}, which is not stored")

    def put_graph(self, poses: dict[int, np.ndarray], depths: dict[int, KeyframeDepth]) -> None:
        """Store the latest poses ((4, 4) world_from_cam) and depths of many keyframes atomically."""
        rows = [("INSERT INTO poses (kf_id, world_from_cam) VALUES (?, ?) ON CONFLICT(kf_id) DO UPDATE SET "
                 "world_from_cam = excluded.world_from_cam, revision = revision + 1",
                 (int(k), to_blob(np.asarray(p, np.float64)))) for k, p in poses.items()]
        rows += [("INSERT INTO depths (kf_id, intrinsics, disparity, static_weight, confidence) VALUES "
                  "(?, ?, ?, ?, ?) ON CONFLICT(kf_id) DO UPDATE SET intrinsics = excluded.intrinsics, "
                  "disparity = excluded.disparity, static_weight = excluded.static_weight, "
                  "confidence = excluded.confidence, revision = revision + 1",
                  (int(k), to_blob(np.asarray(d.intrinsics, np.float64)), to_blob(d.disparity),
                   to_blob(d.static_weight), to_blob(d.confidence))) for k, d in depths.items()]
        self._write(rows)

    def put_basis(self, basis: PcaBasis) -> None:
        """Store a PCA basis under its version."""
        self._write([("INSERT OR REPLACE INTO pca (version, backbone, mean, components) VALUES (?, ?, ?, ?)",
                      (basis.version, basis.backbone, to_blob(basis.mean), to_blob(basis.components)))])

    def set_meta(self, values: dict[str, str]) -> None:
        """Store free-form metadata (voxel size, metric flag, stream name...)."""
        self._write([("INSERT OR REPLACE INTO meta (key, value) VALUES (?, ?)", (k, str(v)))
                     for k, v in values.items()])

    def put_frame_poses(self, rows: list[tuple[int, int, np.ndarray, bool]]) -> None:
        """Store (seq, t_ns, (4, 4) world_from_cam, mapped) frame poses in one transaction; a tracking pose
        (mapped False) never replaces a mapped one."""
        self._write([("INSERT INTO frame_poses (seq, t_ns, world_from_cam, mapped) VALUES (?, ?, ?, ?) "
                      "ON CONFLICT(seq) DO UPDATE SET t_ns = excluded.t_ns, world_from_cam = excluded.world_from_cam, "
                      "mapped = excluded.mapped WHERE excluded.mapped >= frame_poses.mapped",
                      (int(s), int(t), np.asarray(p, "<f8").tobytes(), int(m))) for s, t, p, m in rows])

    def frame_poses(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every stored frame pose, by seq: (N,) seqs, (N,) stamps (ns), (N, 4, 4) world_from_cam."""
        with self._lock:
            rows = self._conn.execute("SELECT seq, t_ns, world_from_cam FROM frame_poses ORDER BY seq").fetchall()
        if not rows:
            return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 4, 4))
        return (np.array([r[0] for r in rows], np.int64), np.array([r[1] for r in rows], np.int64),
                np.frombuffer(b"".join(r[2] for r in rows), "<f8").reshape(-1, 4, 4).copy())

    def put_folded(self, modes: list[tuple[int, int]]) -> None:
        """Record folded keyframes: (kf_id, mode) with mode 2 = with codes, 1 = geometry only, 0 = nothing."""
        self._write([("INSERT OR REPLACE INTO folded (kf_id, mode) VALUES (?, ?)", (int(k), int(m))) for k, m in modes])

    def folded_mode(self, kf_id: int) -> int | None:
        """How keyframe ``kf_id`` was folded (2 with codes, 1 geometry only, 0 nothing); None: not folded."""
        with self._lock:
            row = self._conn.execute("SELECT mode FROM folded WHERE kf_id = ?", (int(kf_id),)).fetchone()
        return None if row is None else int(row[0])

    def delete_keyframe(self, kf_id: int) -> None:
        """Remove a keyframe and everything stored about it."""
        self._write([(f"DELETE FROM {t} WHERE kf_id = ?", (kf_id,))
                     for t in ("keyframes", "depths", "poses", "images", "folded", "thumbnails")])

    def keyframe_ids(self) -> list[int]:
        """Ids of the committed keyframes, ascending."""
        return [r[0] for r in self._conn.execute("SELECT kf_id FROM keyframes ORDER BY kf_id")]

    def image(self, kf_id: int) -> bytes | None:
        """The keyframe's JPEG image, if it was stored."""
        row = self._conn.execute("SELECT jpeg FROM images WHERE kf_id = ?", (kf_id,)).fetchone()
        return None if row is None else bytes(row[0])

    def keyframe_index(self) -> list[KeyframeRow]:
        """Every stored keyframe (folded ones too), ascending id, without reading any array."""
        with self._lock:
            rows = self._conn.execute(
                "SELECT k.kf_id, k.t_ns, k.width, k.height, CASE WHEN k.codes IS NULL THEN -1 ELSE k.pca_version END, "
                "t.kf_id IS NOT NULL FROM keyframes k LEFT JOIN thumbnails t ON t.kf_id = k.kf_id ORDER BY k.kf_id"
            ).fetchall()
        return [KeyframeRow(r[0], r[1], r[2], r[3], r[4], bool(r[5])) for r in rows]

    def thumbnail(self, kf_id: int) -> Thumbnail | None:
        """The keyframe's thumbnail, if one was stored."""
        with self._lock:
            row = self._conn.execute("SELECT jpeg, width, height FROM thumbnails WHERE kf_id = ?",
                                     (int(kf_id),)).fetchone()
        return None if row is None else Thumbnail(bytes(row[0]), int(row[1]), int(row[2]))

    def keyframe_codes(self, kf_id: int) -> tuple[int, np.ndarray | None]:
        """(pca_version, (h, w, K) codes) of a stored keyframe; (-1, None) before its codes come. LookupError if
        the keyframe is not stored. Read from the database: folded keyframes' codes are no longer in memory."""
        with self._lock:
            row = self._conn.execute("SELECT pca_version, codes FROM keyframes WHERE kf_id = ?",
                                     (int(kf_id),)).fetchone()
        if row is None:
            raise LookupError(f"keyframe {kf_id} is not stored")
        return (int(row[0]), from_blob(row[1])) if row[1] is not None else (-1, None)

    def load_static(self) -> StoredMap:
        """The bases and metadata only (no keyframes: `iter_keyframes` streams those)."""
        out = StoredMap()
        with self._lock:
            q = self._conn.execute
            out.bases = {v: PcaBasis(v, from_blob(m), from_blob(c), b)
                         for v, b, m, c in q("SELECT version, backbone, mean, components FROM pca")}
            out.meta = dict(q("SELECT key, value FROM meta"))
        return out

    def iter_keyframes(self, page: int = 64, codes: bool = True) -> Iterator[tuple[list[StoredKeyframe], bool]]:
        """Every keyframe id (of the keyframes, depths and poses tables) in ascending order, ``page`` ids at a time:
        yields (records, whether this is the last page). Each page is its own short read; ``codes=False`` leaves
        the codes unread (content.codes None)."""
        last = -(1 << 62)
        while True:
            with self._lock:
                q = self._conn.execute
                ids = [r[0] for r in q("SELECT kf_id FROM keyframes WHERE kf_id > ? UNION SELECT kf_id FROM depths "
                                       "WHERE kf_id > ? UNION SELECT kf_id FROM poses WHERE kf_id > ? "
                                       "ORDER BY kf_id LIMIT ?", (last, last, last, page))]
                if not ids:
                    yield [], True
                    return
                span = (last, ids[-1])
                where = "WHERE kf_id > ? AND kf_id <= ?"
                kfs = {r[0]: r for r in q(f"SELECT kf_id, t_ns, pca_version, height, width, "
                                          f"{'codes' if codes else 'NULL'}, colours, intrinsics, realtime "
                                          f"FROM keyframes {where}", span)}
                depths = {r[0]: r for r in q("SELECT kf_id, intrinsics, disparity, static_weight, confidence "
                                             f"FROM depths {where}", span)}
                poses = dict(q(f"SELECT kf_id, world_from_cam FROM poses {where}", span))
                folded = dict(q(f"SELECT kf_id, mode FROM folded {where}", span))
            records = []
            for kf_id in ids:
                k, d = kfs.get(kf_id), depths.get(kf_id)
                content = None if k is None else KeyframeContent(kf_id, k[1], from_blob(k[5]), from_blob(k[6]),
                                                                 (k[3], k[4]), k[2] if k[5] is not None else -1)
                depth = None if d is None else KeyframeDepth(from_blob(d[2]), from_blob(d[1]), from_blob(d[3]),
                                                             from_blob(d[4]))
                records.append(StoredKeyframe(kf_id, content, depth, from_blob(poses.get(kf_id)),
                                              None if k is None else from_blob(k[7]), bool(k is not None and k[8]),
                                              folded.get(kf_id)))
            done = len(ids) < page
            yield records, done
            if done:
                return
            last = ids[-1]

    def load(self) -> StoredMap:
        """Everything committed, in one read transaction (a consistent snapshot)."""
        out = StoredMap()
        with self._lock:
            self._conn.execute("BEGIN")
            try:
                self._load_into(out)
            finally:
                self._conn.execute("COMMIT")
        return out

    def _load_into(self, out: StoredMap) -> None:
        q = self._conn.execute
        for kf_id, t_ns, ver, h, w, codes, colours, intr, realtime in q(
            "SELECT kf_id, t_ns, pca_version, height, width, codes, colours, intrinsics, realtime FROM keyframes"
        ):
            out.contents[kf_id] = KeyframeContent(kf_id, t_ns, from_blob(codes), from_blob(colours), (h, w), ver)
            if intr is not None:
                out.intrinsics[kf_id] = from_blob(intr)
            if realtime:
                out.realtime.add(kf_id)
        for kf_id, intr, disp, static, conf in q(
            "SELECT kf_id, intrinsics, disparity, static_weight, confidence FROM depths"
        ):
            out.depths[kf_id] = KeyframeDepth(from_blob(disp), from_blob(intr), from_blob(static), from_blob(conf))
        out.poses = {k: from_blob(p) for k, p in q("SELECT kf_id, world_from_cam FROM poses")}
        out.bases = {v: PcaBasis(v, from_blob(m), from_blob(c), b)
                     for v, b, m, c in q("SELECT version, backbone, mean, components FROM pca")}
        out.meta = dict(q("SELECT key, value FROM meta"))
