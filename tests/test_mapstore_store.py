"""Durable store: round trip, migrations, and crash safety under SIGKILL."""

from __future__ import annotations

import io
import os
import signal
import sqlite3
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from services.mapstore.core.keyframe import KeyframeContent, KeyframeDepth
from services.mapstore.core.scoring import PcaBasis
from services.mapstore.blobs import from_blob, to_blob
from services.mapstore.store import MIGRATIONS, SCHEMA_VERSION, MapStore, migrate, schema_version

REPO = Path(__file__).resolve().parents[1]
INTR = np.array([100.0, 101.0, 63.5, 47.5])


def keyframe(kf_id: int) -> tuple[KeyframeContent, KeyframeDepth, np.ndarray]:
    """Deterministic keyframe data from its id (the crash test's writer makes the same)."""
    rng = np.random.default_rng(kf_id)
    content = KeyframeContent(kf_id, 10**9 * kf_id, rng.normal(size=(12, 16, 32)).astype(np.float16),
                              rng.integers(0, 256, (12, 16, 3), dtype=np.uint8), (96, 128), 1)
    depth = KeyframeDepth(rng.uniform(0.1, 1, (12, 16)).astype(np.float32), INTR,
                          rng.uniform(0, 1, (12, 16)).astype(np.float32), None)
    pose = np.eye(4)
    pose[:3, 3] = rng.normal(size=3)
    return content, depth, pose


def assert_same_keyframe(loaded, kf_id: int) -> None:
    content, depth, pose = keyframe(kf_id)
    got = loaded.contents[kf_id]
    np.testing.assert_array_equal(got.codes, content.codes)
    assert got.codes.dtype == np.float16
    np.testing.assert_array_equal(got.colours, content.colours)
    assert (got.t_ns, got.image_hw, got.pca_version) == (content.t_ns, content.image_hw, content.pca_version)
    np.testing.assert_array_equal(loaded.depths[kf_id].disparity, depth.disparity)
    np.testing.assert_array_equal(loaded.depths[kf_id].static_weight, depth.static_weight)
    assert loaded.depths[kf_id].confidence is None
    np.testing.assert_array_equal(loaded.poses[kf_id], pose)


def write_keyframe(store: MapStore, kf_id: int) -> None:
    content, depth, pose = keyframe(kf_id)
    store.put_keyframe(content, INTR, jpeg=b"\xff\xd8fake")
    store.put_graph({kf_id: pose}, {kf_id: depth})


def test_write_reopen_identical(tmp_path):
    path = tmp_path / "map.db"
    basis = PcaBasis(1, np.arange(8, dtype=np.float32), np.eye(4, 8, dtype=np.float32), "dinov2_vits14")
    with MapStore(path) as store:
        for i in range(5):
            write_keyframe(store, i)
        store.put_basis(basis)
        store.set_meta({"voxel_size": "0.125"})
        newer = np.eye(4)
        newer[0, 3] = 9.0
        store.put_graph({3: newer}, {})
    with MapStore(path) as store:
        loaded = store.load()
        assert store.keyframe_ids() == list(range(5))
        assert store.image(2) == b"\xff\xd8fake"
    for i in (0, 1, 2, 4):
        assert_same_keyframe(loaded, i)
    np.testing.assert_array_equal(loaded.poses[3], newer)
    np.testing.assert_array_equal(loaded.intrinsics[0], INTR)
    assert loaded.meta == {"voxel_size": "0.125"}
    np.testing.assert_array_equal(loaded.bases[1].components, basis.components)
    assert loaded.bases[1].backbone == "dinov2_vits14"


@pytest.mark.parametrize("array", [np.arange(12, dtype=np.float16).reshape(3, 4), np.zeros((0, 3)),
                                   np.ones((2, 3, 4), np.uint8), np.arange(5, dtype=">i4"),
                                   np.asfortranarray(np.arange(6.0).reshape(2, 3))])
def test_blobs_read_back_as_numpy_reads_them(array):
    """from_blob parses each distinct .npy header once: the arrays are np.load's, writable, from our blobs and from
    .npy files numpy writes (a Fortran-ordered one, version 2 and 3 headers included)."""
    for blob in (to_blob(array), _npy(array), _npy(array, version=(2, 0)), _npy(array, version=(3, 0))):
        expected, got = np.load(io.BytesIO(blob)), from_blob(blob)
        assert got.dtype == expected.dtype and got.shape == expected.shape and got.flags.writeable
        np.testing.assert_array_equal(got, expected)
    with pytest.raises(ValueError, match="not an .npy blob"):
        from_blob(b"not numpy at all")


def _npy(array: np.ndarray, version: tuple[int, int] | None = None) -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array(buf, array, version=version, allow_pickle=False)
    return buf.getvalue()


def test_database_is_in_wal_mode_with_current_schema(tmp_path):
    MapStore(tmp_path / "m.db").close()
    conn = sqlite3.connect(tmp_path / "m.db")
    assert conn.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    assert schema_version(conn) == SCHEMA_VERSION == len(MIGRATIONS)


def test_old_schema_is_migrated_keeping_data(tmp_path):
    path = tmp_path / "old.db"
    conn = sqlite3.connect(path, isolation_level=None)
    migrate(conn, target=1)
    content, _, _ = keyframe(7)

    conn.execute("INSERT INTO keyframes VALUES (?, ?, ?, ?, ?, ?, ?)",
                 (7, content.t_ns, 1, 96, 128, to_blob(content.codes), to_blob(content.colours)))
    conn.close()
    with MapStore(path) as store:
        loaded = store.load()
        assert store.image(7) is None
    np.testing.assert_array_equal(loaded.contents[7].codes, content.codes)
    assert 7 not in loaded.intrinsics
    assert schema_version(sqlite3.connect(path)) == SCHEMA_VERSION


WRITER = textwrap.dedent(
    """
    import sys
    from tests.test_mapstore_store import MapStore, write_keyframe
    store = MapStore(sys.argv[1])
    for i in range(100000):
        write_keyframe(store, i)
        print(f"ack {i}", flush=True)
    """
)


@pytest.mark.parametrize("synchronous", ["NORMAL", "FULL"])
def test_every_acknowledged_keyframe_survives_sigkill(tmp_path, synchronous):
    path = tmp_path / "crash.db"
    MapStore(path, synchronous=synchronous).close()  # create with the mode under test
    env = dict(os.environ, PYTHONPATH=str(REPO))
    proc = subprocess.Popen([sys.executable, "-c", WRITER, str(path)], stdout=subprocess.PIPE, text=True,
                            cwd=REPO, env=env)
    acked = -1
    try:
        for line in proc.stdout:
            acked = int(line.split()[1])
            if acked >= 20:
                break
    finally:
        os.kill(proc.pid, signal.SIGKILL)  # mid-stream: it is writing the next keyframe now
        proc.wait()
    assert acked >= 20, "writer died before acknowledging 20 keyframes"
    with MapStore(path) as store:
        assert store._conn.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
        loaded = store.load()
    for i in range(acked + 1):
        assert_same_keyframe(loaded, i)
    for i in loaded.contents:  # anything beyond the last ack is complete or absent, never torn
        if i in loaded.depths:
            assert_same_keyframe(loaded, i)


def test_frame_poses_keep_mappings_revision_over_a_later_tracking_pose(tmp_path):
    from services.common.schema import Poses
    from services.mapstore.poselog import PoseLog

    eye = np.eye(4)
    moved = np.eye(4)
    moved[:3, 3] = (1.0, 2.0, 3.0)
    log = PoseLog()
    log.add(Poses("s", 2, 0, frame_seqs=np.array([2, 0]), stamps_ns=np.array([20, 0]), poses=np.stack([eye, eye]),
                  tracked=True))
    log.add(Poses("s", 2, 0, frame_seqs=np.array([2]), stamps_ns=np.array([20]), poses=moved[None]))  # mapped
    log.add(Poses("s", 2, 0, frame_seqs=np.array([2]), stamps_ns=np.array([20]), poses=eye[None], tracked=True))
    with MapStore(tmp_path / "m.db") as store:
        assert log.flush(store) == 2 and log.flush(store) == 0
        # across flushes too: tracking's late pose of frame 2 does not replace mapping's
        store.put_frame_poses([(2, 20, eye, False), (1, 10, eye, False)])
        seqs, stamps, poses = store.frame_poses()
    assert seqs.tolist() == [0, 1, 2] and stamps.tolist() == [0, 10, 20]
    np.testing.assert_array_equal(poses[2], moved)
    with MapStore(tmp_path / "m.db") as store:  # durable
        assert store.frame_poses()[0].tolist() == [0, 1, 2]
