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

from services.common.own_pages import own_pages

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
