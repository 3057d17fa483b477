"""Frozen sums in files (services/mapstore/frozen_files.py): out of the mapstore's memory, merged and read back a
chunk at a time, in a folder per process that a restart or a killed process does not leave behind."""
from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
import tracemalloc

import numpy as np

from services.mapstore.config import MapstoreSettings
from services.mapstore.core.frozen import FrozenSums
from services.mapstore.core.fusion import make_contribution, merge_contributions
from services.mapstore.frozen_files import FileSums
from services.mapstore.state import MapState

K = 32


def _parts(rng, n, rows):
    return [make_contribution(rng.uniform(0, 40, size=(rows, 3)), rng.uniform(0.1, 1, rows),
                              rng.normal(size=(rows, K)).astype(np.float16), rng.integers(0, 255, (rows, 3)), 0.5)
            for _ in range(n)]


def test_rows_read_back_by_range_as_written(tmp_path):
    store = FileSums(tmp_path / "map.db")
    rng = np.random.default_rng(1)
    a, b = _parts(rng, 2, 300)
    run = store.write([a, b])
    assert store.rows(run) == a.keys.size + b.keys.size
    got = store.read(run, a.keys.size - 5, a.keys.size + 7)
    np.testing.assert_array_equal(got.keys, np.r_[a.keys[-5:], b.keys[:7]])
    np.testing.assert_array_equal(got.codes, np.r_[a.codes[-5:], b.codes[:7]])
    np.testing.assert_array_equal(got.xyz, np.r_[a.xyz[-5:], b.xyz[:7]])
    assert store.read(run, 0, 0).codes.shape == (0, K)
    without = store.write([dataclasses.replace(a, codes=None)])  # a keyframe folded without codes
    assert store.read(without, 0, 3).codes is None
    store.discard(run)
    assert not list(store.folder.glob(f"{run.number}.*"))


def test_a_merge_holds_a_chunk_of_the_stored_sums_not_all_of_them(tmp_path):
    """What the files are for: merging new rows into a version's stored sums reads, sums and writes a chunk at a
    time, so the process never holds the stored sums whole (in memory they are all held, twice while merging)."""
    rng = np.random.default_rng(2)
    stored = _parts(rng, 1, 200_000)[0]  # ~25 MB of sums over ~130k voxels
    new = _parts(rng, 1, 60_000)  # over a quarter of the stored voxels: merged at once
    peaks = {}
    for where in ("memory", "files"):
        frozen = FrozenSums(FileSums(tmp_path / f"{where}.db") if where == "files" else None, min_pending=1,
                            chunk_rows=4096)
        frozen.add(stored)
        tracemalloc.start()
        frozen.add(new[0])
        assert frozen._pending_rows == 0  # merged
        peaks[where] = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        np.testing.assert_array_equal(frozen.contribution().keys, merge_contributions([stored, *new]).keys)
    run_bytes = sum(a.nbytes for a in (stored.keys, stored.weight, stored.xyz, stored.codes, stored.colours,
                                       stored.count))
    assert peaks["memory"] > run_bytes, (peaks, run_bytes)  # the whole run copied at each merge
    assert peaks["files"] < 0.15 * run_bytes, (peaks, run_bytes)


def test_a_merge_at_the_default_chunk_holds_less_than_the_stored_run(tmp_path):
    """Folding keyframe after keyframe into a stored run the size of the 10,000-frame stream's (~55k rows): the
    merges it triggers hold less at once than the run itself (at 16,384 rows a chunk they held 1.7x the run, which
    set the mapstore's high-water once folding began)."""
    rng = np.random.default_rng(3)
    frozen = FrozenSums(FileSums(tmp_path / "map.db"))
    for part in _parts(rng, 40, 1400):  # one folded keyframe's voxels each
        frozen.add(part)
    run_rows, later = frozen._run_rows, _parts(rng, 12, 1400)  # past a quarter of the run: at least one merge
    tracemalloc.start()
    for part in later:
        frozen.add(part)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert frozen._run_rows > run_rows > 40_000  # merged into a run of about the stream's size
    row_bytes = sum(a.itemsize * int(np.prod(a.shape[1:])) for a in dataclasses.astuple(_parts(rng, 1, 1)[0])
                    if a is not None)
    assert peak < 0.85 * run_rows * row_bytes, (peak, run_rows * row_bytes)


def test_a_failed_write_loses_no_rows_and_leaves_no_partial_run(tmp_path):
    """A disk that fills up during a merge: the merge raises, the rows it was merging stay (pending, and the old
    run), its partial files are removed, and the next merge once there is room holds everything."""

    class FillingDisk(FileSums):
        full = False

        def write(self, chunks):
            def failing():
                for n, chunk in enumerate(chunks):
                    if self.full and n == 1:
                        raise OSError(28, "No space left on device")
                    yield chunk
            return super().write(failing())

    store = FillingDisk(tmp_path / "map.db")
    rng = np.random.default_rng(5)
    parts = _parts(rng, 6, 3000)
    frozen = FrozenSums(store, min_pending=1, chunk_rows=1000)
    frozen.add(parts[0])
    files_before = sorted(store.folder.iterdir())
    store.full = True
    try:
        frozen.add(merge_contributions(parts[1:4]))  # over a quarter of the run: merged at once
    except OSError:
        pass
    else:
        raise AssertionError("the merge should have failed")
    assert sorted(store.folder.iterdir()) == files_before  # no partial run
    store.full = False
    frozen.add(parts[4])
    frozen.add(parts[5])
    got, want = frozen.contribution(), merge_contributions(parts)
    np.testing.assert_array_equal(got.keys, want.keys)
    np.testing.assert_allclose(got.weight, want.weight)
    np.testing.assert_array_equal(got.count, want.count)


def test_each_process_has_its_own_folder_and_dead_processes_folders_are_removed(tmp_path):
    db = tmp_path / "map.db"
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    stale = tmp_path / f"map.db.frozen-{int(dead.stdout)}"  # a killed mapstore's folder
    alive = tmp_path / f"map.db.frozen-{os.getppid()}"  # e.g. `kmvipe map export` reading a running map's database
    for folder in (stale, alive):
        folder.mkdir()
        (folder / "0.keys").write_bytes(b"\0" * 8)
    store = FileSums(db)
    assert store.folder == tmp_path / f"map.db.frozen-{os.getpid()}" and store.folder.is_dir()
    assert not stale.exists() and (alive / "0.keys").exists()
    store.write(_parts(np.random.default_rng(0), 1, 10))
    again = FileSums(db)  # the same process opening the map again (a new session): its folder starts empty
    assert not any(again.folder.iterdir())
    again.close()
    assert not again.folder.exists()


def test_the_map_state_keeps_its_folded_sums_beside_its_database_until_closed(tmp_path):
    cfg = MapstoreSettings(db_path=str(tmp_path / "map" / "{stream}.db"), stream="cam0")
    state = MapState(cfg)
    folder = tmp_path / "map" / f"cam0.db.frozen-{os.getpid()}"
    assert state.map.frozen_store is state.frozen_files and state.frozen_files.folder == folder and folder.is_dir()
    state.close()
    assert not folder.exists()
    in_memory = MapState(cfg.model_copy(update={"frozen_sums": "memory"}))
    assert in_memory.map.frozen_store is None and not folder.exists()
    in_memory.close()
