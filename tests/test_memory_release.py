"""Freed heap goes back to the kernel when a service asks (services/common/lifecycle.py): with the allocator tuned
the way ba tunes it, a burst of freed arrays stays resident until ``release_free_memory``, while a freed buffer of
8 MiB or more leaves at once; and ``MemoryRelease`` asks at most once per period."""
from __future__ import annotations

import ctypes
import json
import subprocess
import sys
import textwrap

import pytest

from services.common.lifecycle import MemoryRelease

glibc = pytest.mark.skipif(not sys.platform.startswith("linux") or not hasattr(ctypes.CDLL(None), "malloc_trim"),
                           reason="glibc's malloc_trim")

# what every probe below starts with, in a process of its own (the allocator's settings are per process)
PRELUDE = textwrap.dedent("""
    import json, sys
    import numpy as np
    from services.common import lifecycle
    from services.common.lifecycle import release_free_memory, tune_malloc_for_tensors

    def rss_mb():
        return int(open("/proc/self/statm").read().split()[1]) * 4096 / 2**20
""")


def _probe(script: str, *args: str) -> dict:
    """Run ``PRELUDE + script`` in a fresh interpreter; the JSON line it prints last."""
    out = subprocess.run([sys.executable, "-c", PRELUDE + textwrap.dedent(script), *args], capture_output=True,
                         text=True, timeout=120, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


PROBE = """
    tune_malloc_for_tensors()  # as ba: buffers under 8 MiB from the heap, 512 MiB of freed heap kept
    before = rss_mb()
    burst = [np.ones(256 * 1024 // 8) for _ in range(1200)]  # 300 MiB of 256 KiB arrays, touched
    keep = [np.ones(16) for _ in range(1200)]  # small survivors between them: a fragmented heap, as in a stream
    during = rss_mb()
    del burst
    freed = rss_mb()
    released = release_free_memory()
    after = rss_mb()
    print(json.dumps(dict(before=before, during=during, freed=freed, after=after, released=released)))
"""


@glibc
def test_freed_burst_stays_resident_until_released():
    rss = _probe(PROBE)
    burst = rss["during"] - rss["before"]
    assert burst > 250  # the arrays were really resident
    assert rss["freed"] - rss["before"] > 0.8 * burst  # freed, but the tuned allocator keeps the pages
    assert rss["released"]
    assert rss["after"] - rss["before"] < 0.2 * burst  # given back


M_MMAP_MAX = -4  # glibc's mallopt parameter; 0 turns mmap off (ba's tuning before the fortieth session)

LARGE = f"""
    tune_malloc_for_tensors()
    if sys.argv[1] == "heap-only":  # the tuning before: every buffer from the heap
        lifecycle._mallopt(({M_MMAP_MAX}, 0))
    before = rss_mb()
    big, small, keep = [], [], []
    for _ in range(10):  # a BA's whole-problem fields (16 MiB) and per-slice buffers (2 MiB), with small survivors
        big.append(np.ones(16 * 2**20 // 8))
        small.append(np.ones(2 * 2**20 // 8))
        keep.append(np.ones(16))
    during = rss_mb()
    del big
    big_freed = rss_mb()
    del small
    print(json.dumps(dict(before=before, during=during, big_freed=big_freed, small_freed=rss_mb())))
"""


@glibc
@pytest.mark.parametrize("allocator", ["tuned", "heap-only"])
def test_large_buffers_leave_at_once_small_ones_stay_for_reuse(allocator):
    """ba's tuning: freed 16 MiB buffers go back to the kernel at once, freed 2 MiB ones stay resident for the next
    slice. The control, every buffer from the heap (the tuning before), keeps the large ones too."""
    rss = _probe(LARGE, allocator)
    assert rss["during"] - rss["before"] > 170  # 160 + 20 MiB really resident
    big_kept = rss["big_freed"] - rss["before"]
    if allocator == "tuned":
        assert big_kept < 40  # the large ones left; the small ones (20 MiB) stayed
        assert rss["small_freed"] - rss["before"] > 15  # and stay once freed
    else:
        assert big_kept > 150


def test_release_at_most_once_per_period(monkeypatch):
    calls = []
    monkeypatch.setattr("services.common.lifecycle.release_free_memory", lambda: calls.append(1) or True)
    now = [100.0]
    release = MemoryRelease(10.0, clock=lambda: now[0])
    assert not release.maybe()  # the period counts from the start
    now[0] = 109.9
    assert not release.maybe()
    now[0] = 110.0
    assert release.maybe()
    now[0] = 115.0
    assert not release.maybe()
    release.now()  # an explicit release (end of stream) restarts the period
    now[0] = 124.0
    assert not release.maybe()
    now[0] = 125.0
    assert release.maybe()
    assert len(calls) == 3 and release.count == 3


def test_period_zero_never_releases(monkeypatch):
    calls = []
    monkeypatch.setattr("services.common.lifecycle.release_free_memory", lambda: calls.append(1) or True)
    now = [0.0]
    release = MemoryRelease(0.0, clock=lambda: now[0])
    for t in (1.0, 1e6):
        now[0] = t
        assert not release.maybe()
    release.now()  # an explicit release too (a stream's end): releases are off
    assert not calls
