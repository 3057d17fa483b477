"""Long-lived arrays on pages of their own (services/common/own_pages.py): copies that keep their values and leave
the heap alone, so that bursts of short-lived buffers between them (a BA's slices) find the holes they left."""
from __future__ import annotations

import ctypes
import json
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from services.common.own_pages import lazy_zeros, own_pages, own_pages_packed, release_rows

glibc = pytest.mark.skipif(not sys.platform.startswith("linux") or not hasattr(ctypes.CDLL(None), "mallopt"),
                           reason="glibc's allocator")


@pytest.mark.parametrize("array", [
    np.arange(24, dtype=np.float32).reshape(2, 3, 4),
    np.arange(40, dtype=np.float64).reshape(5, 8)[:, ::3],  # not contiguous
    np.frombuffer(b"\x01\x02\x03\x04", np.uint8),  # read-only, as a decoded message's
    np.zeros((0, 3), np.int64),
    np.array([True, False]),
])
def test_a_copy_with_the_same_values_that_shares_nothing(array):
    kept = own_pages(array)
    assert kept.dtype == array.dtype and kept.shape == array.shape
    np.testing.assert_array_equal(kept, array)
    assert not np.shares_memory(kept, array)
    assert kept.flags.writeable and kept.flags.c_contiguous


def test_a_copy_cast_on_the_way_keeps_the_values_of_the_cast():
    codes = np.linspace(-3, 3, 24, dtype=np.float32).reshape(2, 3, 4)
    kept = own_pages(codes, np.float16)
    assert kept.dtype == np.float16 and kept.shape == codes.shape
    np.testing.assert_array_equal(kept, codes.astype(np.float16))
    assert own_pages(np.zeros((0, 4), np.float32), np.float16).dtype == np.float16


def test_packed_copies_share_one_map_and_keep_their_values():
    """A keyframe's voxel sums (int64 keys, float64 and float32 fields of odd lengths, a missing field) packed
    into one map: every copy equals its source, starts aligned, and writing one leaves its neighbours alone."""
    arrays = [np.arange(7, dtype=np.int64), np.linspace(0, 1, 21).reshape(7, 3), None,
              np.arange(35, dtype=np.float32).reshape(7, 5), np.array([1, 2, 3], np.uint8), np.zeros((0, 3))]
    packed = own_pages_packed(arrays)
    assert packed[2] is None
    bases = set()
    for kept, source in zip(packed, arrays):
        if source is None:
            continue
        assert kept.dtype == source.dtype and kept.shape == source.shape and kept.flags.writeable
        np.testing.assert_array_equal(kept, source)
        assert not np.shares_memory(kept, source)
        assert kept.ctypes.data % 64 == 0 or kept.size == 0
        bases.add(id(_owner(kept)))
    assert len(bases) == 1  # one map behind them all
    packed[1][...] = -1
    np.testing.assert_array_equal(packed[0], arrays[0])
    np.testing.assert_array_equal(packed[3], arrays[3])


def test_where_no_map_can_be_made_the_copy_is_a_plain_one(monkeypatch):
    """At the kernel's limit of maps (or under strict overcommit) ``mmap`` fails: the copy is made in the heap
    instead of failing the keyframe or the BA that keeps it."""
    from services.common import own_pages as module

    def no_map(*args, **kwargs):
        raise OSError(12, "Cannot allocate memory")

    monkeypatch.setattr(module.mmap, "mmap", no_map)
    array = np.arange(12.0).reshape(3, 4)
    kept = own_pages(array)
    np.testing.assert_array_equal(kept, array)
    assert not np.shares_memory(kept, array) and kept.base is None  # its own heap buffer, no map behind it


# 2,000 arrays of 24 KiB (cached flow targets): on pages of their own the heap does not hold them, and their pages
# leave when they are freed; the control, plain copies, fill the heap, which keeps their pages after they are freed
KEPT = textwrap.dedent("""
    import ctypes, json, sys
    import numpy as np
    from services.common.lifecycle import tune_malloc_for_tensors
    from services.common.own_pages import own_pages

    class MallInfo2(ctypes.Structure):
        _fields_ = [(n, ctypes.c_size_t) for n in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                                                   "fsmblks", "uordblks", "fordblks", "keepcost")]

    libc = ctypes.CDLL(None)
    libc.mallinfo2.restype = MallInfo2

    def heap_mb():
        return libc.mallinfo2().uordblks / 2**20

    def rss_mb():
        return int(open("/proc/self/statm").read().split()[1]) * 4096 / 2**20

    tune_malloc_for_tensors()  # as ba: buffers under 8 MiB from the heap, 512 MiB of freed heap kept
    keep = own_pages if sys.argv[1] == "own" else np.array
    source = np.ones(24 * 1024 // 8)
    heap, rss = heap_mb(), rss_mb()
    kept = [keep(source) for _ in range(2000)]
    heap_held, rss_held = heap_mb() - heap, rss_mb() - rss
    del kept
    print(json.dumps(dict(heap_held=heap_held, rss_held=rss_held, rss_after=rss_mb() - rss)))
""")


def _kept(mode: str) -> dict:
    out = subprocess.run([sys.executable, "-c", KEPT, mode], capture_output=True, text=True, timeout=120,
                         check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


@glibc
def test_arrays_on_their_own_pages_stay_out_of_the_heap_and_leave_when_freed():
    own, heap = _kept("own"), _kept("heap")
    assert own["rss_held"] > 40 and heap["rss_held"] > 40  # 47 MB of arrays, resident either way
    assert own["heap_held"] < 5  # ... not in the heap
    assert own["rss_after"] < 5  # and given back when freed
    # the control: in the heap, and resident after they are freed
    assert heap["heap_held"] > 40
    assert heap["rss_after"] > 40


def test_a_keyframe_graph_keeps_its_ba_results_and_flows_each_in_storage_of_its_own():
    """After a BA the graph's poses and depths are its own copies, not views that would keep the BA's stacked
    state (every keyframe of the window at once) alive between BAs, and its cached flow targets likewise."""
    import torch

    from services.ba.core.params import BAParams
    from tests.test_ba_steps import _profile_graph

    seqs = [0, 4, 8]
    graph, world = _profile_graph("rot1", seqs)
    for k, seq in enumerate(seqs):
        graph.poses[k] = torch.from_numpy(np.linalg.inv(world.poses[0]) @ world.poses[seq])
    window = list(range(len(seqs)))
    result = graph.run(window, graph.pairs(window, radius=2), BAParams(iterations=2))
    assert result is not None
    for n, k in enumerate(window):
        for kept, stacked in ((graph.poses[k], result.state.poses), (graph.disparity[k], result.state.disparity)):
            assert torch.equal(kept, stacked[n])
            assert kept.untyped_storage().nbytes() == kept.nbytes
    flow = graph.targets(0, 1)
    for field in flow:
        assert field.untyped_storage().nbytes() == field.nbytes


def _owner(array: np.ndarray):
    """What finally holds ``array``'s memory: a memory map, or the array that owns its heap buffer."""
    while isinstance(array, np.ndarray) and array.base is not None:
        array = array.base
    return array.obj if isinstance(array, memoryview) else array


def test_the_map_keeps_each_keyframes_sums_and_unit_codes_in_storage_of_their_own():
    """What the mapstore's map keeps per live keyframe and rebuilds often (its voxel sums at each re-fusion, its
    unit codes at each PCA refit) lives outside the heap, the sums of one keyframe in one map."""
    import dataclasses
    import mmap

    from services.mapstore.config import MapParams
    from tests.test_mapstore_core import build_map

    m = build_map(MapParams(), n=4)
    assert len(m._contrib) == 4
    for contribution, _ in m._contrib.values():
        owners = {id(_owner(getattr(contribution, f.name))) for f in dataclasses.fields(contribution)}
        assert len(owners) == 1 and isinstance(_owner(contribution.keys), mmap.mmap)
    units = [u for u in m._unit_codes.values() if u is not None]
    assert units and all(isinstance(_owner(u), mmap.mmap) for u in units)


def test_released_rows_read_as_zeros_and_their_pages_leave_the_process():
    """A reserved array whose use shrank: the rows past the ones kept read as zeros, the kept ones keep their
    values, and the process's resident memory falls by about the pages past them."""
    import psutil

    process = psutil.Process()
    array = lazy_zeros((1 << 20, 8), np.float64)  # 64 MiB
    array[:] = 1.5
    before = process.memory_info().rss
    handed_back = release_rows(array, 1 << 18, written_rows=array.shape[0])
    freed = before - process.memory_info().rss
    assert handed_back >= 48 << 20 and freed > 40 << 20, (handed_back, freed)
    assert (array[: 1 << 18] == 1.5).all() and not array[1 << 18 :].any()
    array[-1] = 2.0  # still writable: the page comes back
    assert array[-1, 0] == 2.0


def test_releasing_a_packed_array_leaves_its_neighbour_and_a_heap_array_is_only_zeroed():
    first, second = own_pages_packed([np.ones((3000, 4)), np.full((3000, 4), 7.0)])
    release_rows(first, 10)
    assert (first[:10] == 1).all() and not first[10:].any()
    assert (second == 7.0).all()
    on_heap = np.ones((100, 3))
    assert release_rows(on_heap, 40) == 0
    assert (on_heap[:40] == 1).all() and not on_heap[40:].any()
