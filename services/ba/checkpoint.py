"""ba's durable state: what mapping knows of a stream, written after a keyframe's BA, so that a ba killed
mid-stream (kill -9, OOM, a node lost) resumes in the same world frame instead of starting a new one.

A checkpoint is the stream's :class:`BaState` as of the highest frame seq mapping had handled (``last_seq``): the
frontend (keyframe graph, window, depths, intrinsics, frame poses), the PCA bases and version, codes that came
before their keyframe, and the anchors tracking left for mapping. Tracking's own state is not kept: it takes
mapping's newest reference on restart. ba reports that seq as ``durable`` in its progress messages; features keeps
what it sent after it and sends it again when a new ba instance reports a lower seq (services/features/replay.py),
so nothing features sent is lost.

One file per (stream, session), replaced whole: written to a temporary file, flushed to disk, then renamed over
the last one (an atomic rename on POSIX), so a kill at any moment leaves the previous checkpoint or the new one,
never half of either. A file rather than a database because there is exactly one value per key, always replaced
whole. A session's checkpoint is removed at its end of stream."""
from __future__ import annotations

import io
import logging
import os
import time
from dataclasses import dataclass
from pathlib import Path

import torch

log = logging.getLogger(__name__)

# BaState fields a checkpoint keeps (the rest is per process: counters, the basis fetcher, the inbox backlog)
KEPT = ("frontend", "pca_version", "bases", "last_seq", "keyframes", "keyframes_seen", "early_codes", "merged",
        "anchors")


@dataclass(frozen=True)
class Checkpoint:
    seq: int  # the highest frame seq it holds
    fields: dict  # BaState field -> value


def snapshot(state) -> bytes:
    """``state``'s kept fields, serialised (on the mapping thread, so the graph does not change under it)."""
    fields = {name: getattr(state, name) for name in KEPT}
    fields["anchors"] = dict(fields["anchors"])  # tracking fills it on its own thread: a copy taken at once
    buffer = io.BytesIO()
    torch.save({"seq": state.last_seq, "fields": fields}, buffer)
    return buffer.getvalue()


def restore(blob: bytes, device: torch.device) -> Checkpoint:
    """A checkpoint from :func:`snapshot`'s bytes: tensors saved on an accelerator go to ``device``, those saved
    on the CPU stay there (ba keeps flow targets, codes and priors on the CPU on purpose: new ones meet them)."""
    def place(storage, location: str):
        return storage if location.startswith("cpu") or device.type == "cpu" else storage.to(device=device)

    data = torch.load(io.BytesIO(blob), map_location=place, weights_only=False)  # our own file, not a download
    fields = data["fields"]
    frontend = fields.get("frontend")
    if frontend is not None:  # pickled with the device it ran on, which another machine may not have
        frontend.device = device
        if frontend.graph is not None:
            frontend.graph.device = device
    return Checkpoint(int(data["seq"]), fields)


def path_for(directory: str | Path, stream: str, session: str) -> Path:
    return Path(directory) / f"{stream}.{session or 'nosession'}.ckpt"


def write(path: Path, blob: bytes) -> None:
    """Replace ``path`` with ``blob`` atomically and durably."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    with open(tmp, "wb") as f:
        f.write(blob)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def read(path: Path) -> bytes | None:
    try:
        return path.read_bytes()
    except FileNotFoundError:
        return None


def pending(directory: str | Path, max_age_s: float = 3600.0) -> list[tuple[str, str]]:
    """(stream, session) of every checkpoint in ``directory``: streams killed before their end, to resume at start.
    Checkpoints older than ``max_age_s`` are of streams nobody will finish: removed."""
    found = []
    for path in sorted(Path(directory).glob("*.ckpt")) if directory else []:
        stream, _, session = path.stem.partition(".")
        if time.time() - path.stat().st_mtime > max_age_s:
            log.info("stale checkpoint removed", extra={"path": str(path)})
            path.unlink(missing_ok=True)
        elif stream and session and session != "nosession":
            found.append((stream, session))
    return found


class Checkpointer:
    """When to checkpoint a stream's state, where, and what the last one holds (``durable``)."""

    def __init__(self, directory: str, stream: str, session: str | None, period_s: float):
        self.path = path_for(directory, stream, session or "") if directory else None
        self.period_s = period_s
        self.durable = -1  # the highest frame seq the newest checkpoint holds
        self._last = float("-inf")
        self.seconds = 0.0  # time spent writing checkpoints (logged at the end of a stream)
        self.written = 0

    @property
    def enabled(self) -> bool:
        return self.path is not None

    def load(self, device: torch.device) -> Checkpoint | None:
        if self.path is None or (blob := read(self.path)) is None:
            return None
        try:
            ckpt = restore(blob, device)
        except Exception:  # a checkpoint that does not load (another version of the code): start afresh
            log.exception("checkpoint unreadable; starting the stream's state afresh", extra={"path": str(self.path)})
            return None
        self.durable = ckpt.seq
        return ckpt

    def due(self, now: float | None = None) -> bool:
        return self.path is not None and (now or time.monotonic()) - self._last >= self.period_s

    def save(self, state) -> None:
        began = time.monotonic()
        blob = snapshot(state)
        write(self.path, blob)
        self._last = time.monotonic()
        self.durable = state.last_seq
        self.seconds += self._last - began
        self.written += 1
        log.debug("checkpoint", extra={"seq": state.last_seq, "mb": round(len(blob) / 2**20, 1),
                                       "s": round(self._last - began, 3)})

    def remove(self) -> None:
        if self.path is not None:
            self.path.unlink(missing_ok=True)
            self.durable = -1
