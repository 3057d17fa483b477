"""The one error boundary of a service process: logging, signals, the bus, the metrics and health endpoints, and a
clear exit on bad settings."""
from __future__ import annotations

import logging
import re
import sys
import threading
from typing import Callable

from pydantic import ValidationError

from . import allocator, metrics
from .bus import Bus
from .config import BusSettings, MetricsSettings
from .errors import KmVipeError
from .lifecycle import limit_blas_threads, stop_on_signals
from .logs import setup_logging

log = logging.getLogger(__name__)

ServiceBody = Callable[[Bus, threading.Event], "int | object"]

_STREAM_THREAD = re.compile(r"^stream-(?P<stream>[A-Za-z0-9_\-]{1,64})(?:/|$)")
"""A stream's thread: ``stream-<name>`` (a StreamHost worker, services/common/streams.py) or ``stream-<name>/<role>``
(a thread that worker starts)."""


class StreamField(logging.Filter):
    """Gives a record logged on a stream's thread the ``stream`` field when it does not name one, so every line a
    multi-stream service logs for a stream carries it."""

    def filter(self, record: logging.LogRecord) -> bool:
        if not hasattr(record, "stream"):
            match = _STREAM_THREAD.match(record.threadName or "")
            if match is not None:
                record.stream = match["stream"]
        return True


def service_main(name: str, body: ServiceBody, tune_malloc: Callable[[], None] | None = None,
                 blas_threads: int | None = None) -> int:
    """Run ``body(bus, stop)`` as service ``name``; returns the process exit code (body's int, else 0).

    It first puts the process on the service's allocator (:func:`services.common.allocator.ensure`), so every way
    of starting a service (``kmvipe service``, the runner, ``python -m services.NAME``) honours that setting.
    Bad settings and known errors end the process with one message and exit code 2, never a traceback.
    ``tune_malloc`` tunes the allocator for what the service holds, one of :mod:`services.common.lifecycle`'s
    (``tune_malloc_for_frames``: frame-sized buffers and the map's arrays; ``_for_tensors``: large tensor
    temporaries); None leaves glibc's defaults.
    ``blas_threads`` caps numpy's BLAS pool (``limit_blas_threads``; None leaves it).
    With ``KMVIPE_METRICS_PORT`` set, ``/metrics``, ``/livez`` and ``/readyz`` are served while the bus is open
    (:mod:`services.common.metrics`).
    """
    try:
        allocator.ensure(name)  # first: may execute this process again on its allocator, same pid and arguments
    except KmVipeError as exc:  # a bad KMVIPE_MALLOC_ALLOCATOR, or one that is not installed
        print(f"{name}: {exc}", file=sys.stderr)
        return 2
    try:
        setup_logging(name)
    except (ValidationError, KmVipeError) as exc:  # a bad [log] table or KMVIPE_CONFIG file
        print(f"{name}: invalid settings: {exc}", file=sys.stderr)
        return 2
    for handler in logging.getLogger().handlers:
        handler.addFilter(StreamField())
    stop = stop_on_signals()
    log.info(f"{name} starting", extra={"allocator": allocator.in_use()})  # services.common.allocator
    if tune_malloc is not None:
        tune_malloc()
    if blas_threads is not None:
        limit_blas_threads(blas_threads)
    try:
        endpoints = MetricsSettings()
        with Bus(BusSettings(), name) as bus, metrics.serving(endpoints, bus):
            result = body(bus, stop)
    except ValidationError as exc:
        print(f"{name}: invalid settings (check the KMVIPE_* environment variables and the KMVIPE_CONFIG file):\n{exc}",
              file=sys.stderr)
        return 2
    except KmVipeError as exc:
        print(f"{name}: {exc}", file=sys.stderr)
        return 2
    return result if isinstance(result, int) else 0
