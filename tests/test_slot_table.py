"""The voxel grid's key → slot index (services/mapstore/core/slot_table.py) against a dict doing the same."""

import numpy as np
import pytest

from services.mapstore.core.fusion import voxel_keys
from services.mapstore.core.slot_table import MAX_LOAD, REBUILD_LOAD, SlotTable


def _check(table: SlotTable, truth: dict[int, int], absent: np.ndarray) -> None:
    keys = np.fromiter(truth, np.int64, len(truth))
    np.testing.assert_array_equal(table.lookup(keys), np.fromiter(truth.values(), np.int64, len(truth)))
    np.testing.assert_array_equal(table.lookup(absent), -1)
    assert len(table) == len(truth)
    stored_keys, stored_slots = table.items()
    assert dict(zip(stored_keys.tolist(), stored_slots.tolist())) == truth


def test_random_inserts_removals_and_moves_match_a_dict():
    rng = np.random.default_rng(7)
    table, truth = SlotTable(capacity=4), {}  # a tiny start: every bucket collides and the table grows many times
    pool = voxel_keys(rng.integers(-300, 300, (20000, 3)))  # real packed voxel coordinates, clustered like a map
    pool = np.unique(pool)
    rng.shuffle(pool)
    next_slot = 0
    for step in range(60):
        present = np.fromiter(truth, np.int64, len(truth))
        if present.size and step % 3 == 2:  # remove a random share, then reinsert some of them later
            gone = rng.choice(present, size=present.size // 3, replace=False)
            table.remove(gone)
            for k in gone.tolist():
                del truth[k]
        elif present.size and step % 5 == 4:  # move some keys to other slots (the grid's compaction)
            moved = rng.choice(present, size=present.size // 4, replace=False)
            slots = rng.integers(0, 1 << 30, moved.size)
            table.assign(moved, slots)
            truth.update(zip(moved.tolist(), slots.tolist()))
        else:
            candidates = pool[rng.integers(0, pool.size, 700)]
            new = np.unique(candidates[table.lookup(candidates) < 0])
            slots = np.arange(next_slot, next_slot + new.size)
            next_slot += new.size
            table.insert(new, slots)
            truth.update(zip(new.tolist(), slots.tolist()))
        absent = np.setdiff1d(pool[:2000], np.fromiter(truth, np.int64, len(truth)))
        _check(table, truth, absent)
        assert len(table) <= MAX_LOAD * table.buckets


def test_removed_buckets_are_reused_without_growing_the_table():
    table = SlotTable(capacity=1000)
    buckets = table.buckets
    keys = np.arange(1000, dtype=np.int64) * 977
    for round_ in range(20):  # a person's voxels carved away and others taking their place, again and again
        shifted = keys + round_ * 10_000_000
        table.insert(shifted, np.arange(1000))
        table.remove(shifted)
    assert len(table) == 0 and table.buckets == buckets
    table.insert(keys, np.arange(1000))
    np.testing.assert_array_equal(table.lookup(keys), np.arange(1000))


def test_the_largest_packed_keys_and_bad_input():
    table = SlotTable()
    top = voxel_keys(np.array([[2**20 - 1] * 3, [-(2**20)] * 3, [0, 0, 0]]))
    table.insert(top, np.array([5, 6, 7]))
    np.testing.assert_array_equal(table.lookup(top), [5, 6, 7])
    with pytest.raises(ValueError, match=">= 0"):
        table.insert(np.array([-3]), np.array([1]))
    with pytest.raises(KeyError, match="1 keys"):
        table.remove(np.array([top[0], 12345]))
    np.testing.assert_array_equal(table.lookup(top), [5, 6, 7])  # a failed removal removed nothing


def test_a_map_sized_table_costs_a_fraction_of_a_dict():
    keys = np.unique(np.random.default_rng(3).integers(0, 2**62, 64000))
    table = SlotTable()
    for chunk in np.array_split(keys, 30):  # as keyframes add voxels
        table.insert(chunk, np.arange(chunk.size))
    # 12 bytes a bucket at a load of at least REBUILD_LOAD / 2; a dict of Python ints took ~120 B a key
    assert REBUILD_LOAD / 2 <= keys.size / table.buckets <= MAX_LOAD
    assert 12 * table.buckets / keys.size < 60
