"""Clean shutdown: SIGTERM/SIGINT set a stop event that the service loop watches."""
from __future__ import annotations

import ctypes
import logging
import signal
import threading

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


def tune_malloc_for_frames() -> None:
    """glibc: serve ~1 MB message buffers from the already-mapped heap instead of fresh mmap pages, whose page
    faults cost ~2 ms per raw 640×480 frame encode (→ ~0.1 ms; bench/bus.py --malloc tuned). Each process may
    keep up to 128 MiB of freed memory. Called once by each service's main, never at import."""
    try:
        libc = ctypes.CDLL(None)
    except OSError:
        return
    if hasattr(libc, "mallopt"):  # glibc only
        libc.mallopt(M_MMAP_THRESHOLD, 32 << 20)
        libc.mallopt(M_TRIM_THRESHOLD, 128 << 20)
