"""Telling that a consumer restarted from its reports: each start of a worker reports (credit, progress) under a
name of its own, so a name not heard before, after another one of the same kind, is a restarted instance that
has lost what was in flight to its predecessor (features resends to ba and the mapstore, ingest to features, ba
its end of stream to the mapstore)."""
from __future__ import annotations

import secrets
import threading


def consumer_name(service: str, instance: str) -> str:
    """The name a worker reports under: the service, its process instance, and a part new at every start."""
    return f"{service}-{instance}.{secrets.token_hex(3)}"


class Restarts:
    """The instances of one kind of consumer (names starting with ``prefix``) heard from so far."""

    def __init__(self, prefix: str):
        self.prefix = prefix
        self._names: set[str] = set()
        self._lock = threading.Lock()

    def replaced_by(self, consumer: str) -> list[str]:
        """The earlier instances ``consumer`` replaces: [] unless it is new and another one came before it."""
        if not consumer.startswith(self.prefix):
            return []
        with self._lock:
            if consumer in self._names:
                return []
            replaced = sorted(self._names)
            self._names = {consumer}
            return replaced
