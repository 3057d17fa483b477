"""Fetching a PCA basis version that no ``pca`` message brought, from the features ``pca`` queryable.

mapstore and ba both need every version their keyframes name (services/common/pca_codes.py); a consumer that
joined late, restarted, or lost a message asks ``kmvipe/<s>/pca?version=<n>``.
"""
from __future__ import annotations

import logging
import time
from collections import Counter
from dataclasses import dataclass
from typing import Callable, Container

from . import keys
from .bus import Bus
from .errors import DecodeError, ServiceTimeout
from .schema import PcaBasis, decode

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FetchParams:
    """How a consumer asks features' ``pca`` queryable for a basis version no ``pca`` message brought."""

    grace_s: float = 0.3
    """Wait this long after a keyframe names an unknown version before asking: the ``pca`` message is usually
    just behind it (Zenoh orders messages per key only)."""
    timeout_s: float = 0.5
    """Longest wait for one reply; the service loop is blocked meanwhile."""
    retry_s: float = 2.0
    """Ask again this long after a failed request for the same version."""


class BasisFetch:
    """The basis versions keyframes named but no ``pca`` message brought, when each may next be asked for, and
    counts of what was fetched and of failed requests (logged, never fatal)."""

    def __init__(self, params: FetchParams = FetchParams()) -> None:
        self.params = params
        self.next_try: dict[int, float] = {}  # version -> monotonic time of its next request
        self.fetched: Counter[int] = Counter()  # version -> bases fetched from the queryable
        self.failures: Counter[str] = Counter()  # reason (timeout | error_reply | bad_reply) -> failed requests
        self._reported: set[tuple[int, str]] = set()  # (version, reason) logged as a warning (then debug only)

    def want(self, version: int) -> None:
        self.next_try.setdefault(version, time.monotonic() + self.params.grace_s)

    def due(self, known: Container[int]) -> list[int]:
        """Versions to ask for now (ascending); versions that arrived meanwhile are forgotten."""
        for version in [v for v in self.next_try if v in known]:
            del self.next_try[version]
        now = time.monotonic()
        return sorted(v for v, t in self.next_try.items() if t <= now)

    def run_due(self, bus: Bus, stream: str, known: Container[int], on_basis: Callable[[PcaBasis], object]) -> None:
        """Ask features for every due version and hand each reply to ``on_basis`` (the ``pca`` handler). A
        timeout (features down) postpones the whole round, so the loop blocks ≤ ``timeout_s`` per ``retry_s``."""
        for version in self.due(known):
            try:
                msg = decode(bus.request(f"{keys.topic(stream, keys.PCA)}?version={version}",
                                         timeout=self.params.timeout_s, service="features"), PcaBasis)
                if msg.version != version:
                    raise DecodeError(f"asked for PCA basis version {version}, got {msg.version}")
            except (ServiceTimeout, RuntimeError, DecodeError) as exc:
                reason = "timeout" if isinstance(exc, ServiceTimeout) else \
                    "error_reply" if isinstance(exc, RuntimeError) else "bad_reply"
                self._failed(version, reason, stream, exc)
                if reason == "timeout":
                    return
                continue
            self.fetched[version] += 1
            log.info("PCA basis fetched from features", extra={"stream": stream, "pca_version": version})
            on_basis(msg)

    def _failed(self, version: int, reason: str, stream: str, exc: Exception) -> None:
        self.failures[reason] += 1
        retry_at = time.monotonic() + self.params.retry_s
        self.next_try[version] = retry_at
        if reason == "timeout":  # the rest of the round would time out too
            self.next_try.update({v: max(t, retry_at) for v, t in self.next_try.items()})
        first = (version, reason) not in self._reported
        self._reported.add((version, reason))
        log.log(logging.WARNING if first else logging.DEBUG, "PCA basis fetch failed; asking again later", extra={
            "stream": stream, "pca_version": version, "reason": reason, "error": str(exc),
            "failures": sum(self.failures.values()), "retry_s": self.params.retry_s})
