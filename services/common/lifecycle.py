"""Clean shutdown: SIGTERM/SIGINT set a stop event that the service loop watches."""
from __future__ import annotations

import ctypes
import gc
import logging
import signal
import threading
import time

from .allocator import in_use

log = logging.getLogger(__name__)


def stop_on_signals(stop: threading.Event | None = None) -> threading.Event:
    """Install SIGTERM/SIGINT handlers (main thread only) that set and return ``stop``."""
    stop = stop or threading.Event()

    def _handler(signum, _frame):
        log.info("stopping on signal", extra={"signal": signal.Signals(signum).name})
        stop.set()

    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, _handler)
    return stop


M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3
M_ARENA_MAX = -8


def _mallopt(*settings: tuple[int, int]) -> None:
    """glibc's ``mallopt(param, value)`` for each pair; nothing where the C library is not glibc."""
    try:
        libc = ctypes.CDLL(None)
    except OSError:
        return
    if hasattr(libc, "mallopt"):  # glibc only
        for param, value in settings:
            libc.mallopt(param, value)


def tune_malloc_for_frames() -> None:
    """glibc: serve ~1 MB message buffers from the already-mapped heap instead of fresh mmap pages, whose page
    faults cost ~2 ms per raw 640×480 frame encode (→ ~0.1 ms; bench/bus.py --malloc tuned). Each process may
    keep up to 128 MiB of freed memory. Called once by each service's main, never at import."""
    _mallopt((M_MMAP_THRESHOLD, 32 << 20), (M_TRIM_THRESHOLD, 128 << 20))


def tune_malloc_for_tensors(keep_mib: int = 512, own_pages_mib: int = 8) -> None:
    """glibc: keep tensor buffers in the heap between uses, but give the largest pages of their own. Dense BA on
    the CPU allocates tens of temporaries per iteration; fresh mmap pages cost a page fault per 4 KiB, which made
    an elementwise product 6x slower than on reused memory and a BA iteration ~2x slower (docs/BENCHMARKS.md, BA
    core). So buffers under ``own_pages_mib`` come from the heap, which keeps up to ``keep_mib`` of freed heap
    (bench/ba.py: 512 kept a 25-keyframe window's speed when every buffer came from the heap). Buffers of
    ``own_pages_mib`` and more are mmapped and go back to the kernel when freed: a background BA's whole-problem
    fields (one (edges, pixels) field is 10 MB at 820 edges of 48x64) left holes that later BAs touched again, and
    ba's RSS peaked with ~600 MB of free heap beside ~870 MB in use. 4 MiB made KITTI's 90-keyframe BA 1.5x
    slower (its frequent per-slice buffers got fresh pages); 8 MiB was as fast as the heap there and on an
    840-edge BA at 48x64, which peaked ~90 MB lower (docs/BENCHMARKS.md, fortieth session). Called by a service's
    main or a bench, never at import."""
    # every thread that allocates gets an arena of its own, each keeping its own freed heap: ba's tracking,
    # mapping and Zenoh threads held ~1.1 GB at 1,500 synthetic frames with the default (8 x cores), 0.95 GB with two.
    # A fixed mmap threshold also stops glibc from raising it after each large free (its dynamic default would
    # soon serve everything from the heap again)
    _mallopt((M_MMAP_THRESHOLD, own_pages_mib << 20), (M_TRIM_THRESHOLD, keep_mib << 20), (M_ARENA_MAX, 2))


def release_free_memory() -> bool:
    """Give the pages of freed heap back to the kernel now: glibc's ``malloc_trim(0)`` (since glibc 2.8 it also
    releases free pages inside every arena, not only at the heap's top), or TCMalloc's ``ReleaseFreeMemory`` in a
    process that runs on it (:mod:`services.common.allocator`). The tunings above keep freed heap for speed, so a
    process's RSS only ever grows: a one-off burst (a model parsed and compiled at load, an end-of-stream BA) stays
    resident, and over a long stream glibc's heap fragments into holes nobody reuses (ba: +41 % from 1,000 to 10,000
    synthetic frames in three steps). Called between bursts, never inside one: the next burst faults its pages in
    again (~0.2 s per 500 MB). Returns whether anything was released (TCMalloc does not say: True)."""
    gc.collect()  # cycles hold tensors and arrays too; free them before trimming
    try:
        libc = ctypes.CDLL(None)
    except OSError:
        return False
    if in_use() == "tcmalloc":  # preloaded (services.common.allocator): glibc's heap is not in use
        libc.MallocExtension_ReleaseFreeMemory()
        return True
    if not hasattr(libc, "malloc_trim"):  # not glibc
        return False
    return bool(libc.malloc_trim(0))


class Period:
    """A loop's work done at most once per ``period_s`` (0: every time): :meth:`due` says whether the period has
    passed since the work was last due (or :meth:`restart`), and starts it again when it has."""

    def __init__(self, period_s: float, clock=None):
        self.period_s = period_s
        self._clock = clock or time.monotonic
        self._last = self._clock()

    def due(self) -> bool:
        now = self._clock()
        if now - self._last < self.period_s:  # period 0: always due, unless held
            return False
        self._last = now
        return True

    def restart(self) -> None:
        self._last = self._clock()

    def hold(self, seconds: float) -> None:
        """The work is not due again for at least ``seconds`` from now (nor before the period has passed)."""
        self._last = max(self._last, self._clock() + seconds - self.period_s)

    def hold_after(self, work_s: float, max_share: float) -> None:
        """Work that just took ``work_s`` seconds gets at most ``max_share`` (0–1] of the time: it is not due again
        for work_s·(1/max_share − 1) seconds (nor before the period has passed)."""
        self.hold(work_s * (1 / max_share - 1))


class MemoryRelease:
    """When a long-running loop calls :func:`release_free_memory`: at most once per ``period_s`` (0: never), at a
    point the caller chooses (between two units of work)."""

    def __init__(self, period_s: float, clock=None):
        self.period_s = period_s
        self._period = Period(period_s, clock)
        self.count = 0
        # TCMalloc reuses what a burst freed, by size class, for the next one: a periodic release would only make
        # that burst fault its pages in again. ba ran its 5,000-frame check on TCMalloc without one (+3.5 %, against
        # glibc's +7.4 % with one every 10 s; docs/BENCHMARKS.md, forty-seventh session)
        self.periodic = in_use() == "glibc"

    def maybe(self) -> bool:
        """Release now if the period has passed since the last release (glibc's heap only: see ``periodic``);
        True when it ran."""
        if self.period_s <= 0 or not self.periodic or not self._period.due():
            return False
        self._release()
        return True

    def now(self) -> None:
        """Release now (after a burst the caller knows of, e.g. a stream's end), unless releases are off."""
        if self.period_s <= 0:
            return
        self._period.restart()
        self._release()

    def _release(self) -> None:
        release_free_memory()
        self.count += 1


def limit_blas_threads(threads: int = 1) -> None:
    """Cap numpy's BLAS thread pool for the rest of the process. A service doing many small matmuls next to
    others on few cores loses to the pool's spinning threads (a 3000×32 by 32×32 product: 7 ms with the default
    pool on the idle 2-core machine, 2 ms with one thread). Called by a service's main, never at import."""
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=threads, user_api="blas")


def nice_this_thread(niceness: int) -> None:
    """Set the scheduling niceness of the calling thread (Linux schedules threads on their own; elsewhere, or
    without the right to lower it, this logs and leaves it). Threads this one starts later inherit it."""
    import os

    if niceness == 0 or not hasattr(os, "setpriority"):
        return
    try:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), niceness)
    except OSError as exc:
        log.info("thread priority left unchanged", extra={"niceness": niceness, "error": str(exc)})
