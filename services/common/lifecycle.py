"""Clean shutdown: SIGTERM/SIGINT set a stop event that the service loop watches."""
from __future__ import annotations

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
