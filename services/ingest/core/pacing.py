"""Flow control of ingest: credit from consumers, and the decision to send, wait or drop a frame.

Pure logic: time is passed in, nothing here sleeps or talks to the bus.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum


class Decision(Enum):
    SEND = "send"
    WAIT = "wait"  # lossless: not enough credit yet
    DROP = "drop"  # realtime: downstream is behind


@dataclass
class CreditLedger:
    """Highest frame seq each consumer can take, with the time it said so.

    The stream may advance to the *smallest* grant among live consumers, so no consumer is overrun. A consumer
    silent for longer than ``ttl_s`` is forgotten (it left or died) and stops holding the stream back.
    """

    ttl_s: float
    grants: dict[str, tuple[int, float]] = field(default_factory=dict)

    def grant(self, consumer: str, seq: int, now: float) -> None:
        previous = self.grants.get(consumer, (-1, now))[0]
        self.grants[consumer] = (max(previous, seq), now)

    def expire(self, now: float) -> None:
        for consumer in [c for c, (_, t) in self.grants.items() if now - t > self.ttl_s]:
            del self.grants[consumer]

    def limit(self, now: float) -> int:
        """Highest seq that may be sent now; -1 when no consumer is live."""
        self.expire(now)
        return min((seq for seq, _ in self.grants.values()), default=-1)


def decide(seq: int, limit: int, lossless: bool) -> Decision:
    """Send frame ``seq`` if credit covers it; else wait (lossless) or drop (realtime)."""
    if seq <= limit:
        return Decision.SEND
    return Decision.WAIT if lossless else Decision.DROP


@dataclass
class IngestCounters:
    """What the ingest service reports at the end (and in its EOS)."""

    read: int = 0
    sent: int = 0
    dropped: int = 0
    corrupt: int = 0
