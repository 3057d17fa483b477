"""Frozen sums kept in files (a `SumsStore` of services/mapstore/core/frozen.py): folded keyframes' voxel sums
out of the mapstore's memory.

A run is one raw file per field (``<n>.keys``, ``<n>.weight``, ...) in a folder of their own; rows are read back by
range with ``numpy.fromfile``, so only the rows asked for enter the process (a memory map would keep every page it
touched resident until unmapped). The files are derived state: a restarted mapstore folds its stored keyframes
again. So each process has a folder of its own beside the database (``<db>.frozen-<pid>``: a ``kmvipe map export``
may read a database a running mapstore writes), emptied when a store opens it and removed when it closes; the
folders of processes no longer alive (killed) are removed then too.
"""
from __future__ import annotations

import dataclasses
import itertools
import os
import shutil
from contextlib import ExitStack
from pathlib import Path
from typing import Iterable, NamedTuple

import numpy as np

from services.mapstore.core.fusion import Contribution

_FIELDS = [f.name for f in dataclasses.fields(Contribution)]


class _Run(NamedTuple):
    number: int
    rows: int
    layout: dict[str, tuple[np.dtype, tuple[int, ...]] | None]  # per field: dtype and row shape; None: absent


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


class FileSums:
    """Runs of frozen rows in this process's folder beside ``db_path`` (created; any earlier content removed)."""

    def __init__(self, db_path: str | Path) -> None:
        db_path = Path(db_path)
        prefix = f"{db_path.name}.frozen-"
        self.folder = db_path.with_name(f"{prefix}{os.getpid()}")
        for other in db_path.parent.glob(f"{prefix}*"):
            pid = other.name[len(prefix):]
            if other == self.folder or (pid.isdigit() and not _alive(int(pid))):
                shutil.rmtree(other, ignore_errors=True)
        self.folder.mkdir(parents=True)
        self._numbers = itertools.count()

    def _path(self, number: int, name: str) -> Path:
        return self.folder / f"{number}.{name}"

    def write(self, chunks: Iterable[Contribution]) -> _Run:
        number, rows, layout = next(self._numbers), 0, None
        with ExitStack() as files:
            try:
                for chunk in chunks:
                    if layout is None:
                        layout = {name: None if getattr(chunk, name) is None else
                                  (getattr(chunk, name).dtype, getattr(chunk, name).shape[1:]) for name in _FIELDS}
                        out = {name: files.enter_context(open(self._path(number, name), "wb"))
                               for name in _FIELDS if layout[name]}
                    for name, f in out.items():
                        np.ascontiguousarray(getattr(chunk, name), layout[name][0]).tofile(f)
                    rows += chunk.keys.size
            except BaseException:  # no partial run is left behind (a full disk)
                files.close()
                self.discard(_Run(number, rows, layout or {}))
                raise
        if layout is None:
            raise ValueError("a run needs at least one chunk")
        return _Run(number, rows, layout)

    def rows(self, run: _Run) -> int:
        return run.rows

    def read(self, run: _Run, start: int, stop: int) -> Contribution:
        stop = min(stop, run.rows)
        count = max(stop - start, 0)

        def field(name: str) -> np.ndarray | None:
            if run.layout[name] is None:
                return None
            dtype, shape = run.layout[name]
            width = int(np.prod(shape)) if shape else 1
            data = np.fromfile(self._path(run.number, name), dtype, count=count * width,
                               offset=start * width * dtype.itemsize) if count else np.zeros(0, dtype)
            return data.reshape((count, *shape))

        return Contribution(*(field(name) for name in _FIELDS))

    def discard(self, run: _Run) -> None:
        for name in _FIELDS:
            self._path(run.number, name).unlink(missing_ok=True)

    def close(self) -> None:
        """Remove the folder and every run in it."""
        shutil.rmtree(self.folder, ignore_errors=True)
