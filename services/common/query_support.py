"""Which semantic queries a map answers, and why: one vocabulary for the run's summary (services/runner/semantics.py)
and the gateway's ``/v1/streams`` (services/query_api/textpath.py)."""
from __future__ import annotations

from dataclasses import asdict, dataclass

EXAMPLE_WHY = "pick a region of a keyframe in the viewer, or POST /v1/streams/<s>/query/keyframe"
ORACLE_WHY = ("oracle: the synthetic world's ground-truth label vectors stand in for DINO and the language model "
              "(a test double, not a learned model)")


@dataclass(frozen=True)
class QuerySupport:
    """What a map answers: text queries and region (example) queries, each with the reason."""

    text: bool
    text_why: str
    example: bool
    example_why: str
    oracle: bool = False

    def line(self) -> str:
        """``text: available — …; example: available — …``, the form the CLI, summary and API use."""
        def word(ok: bool) -> str:
            return "available" if ok else "unavailable"
        return f"text: {word(self.text)} — {self.text_why}; example: {word(self.example)} — {self.example_why}"

    def as_dict(self) -> dict:
        return asdict(self)
