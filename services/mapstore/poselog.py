"""The stream's trajectory in the map database: every frame pose ba publishes, so it outlives the gateway.

The gateway keeps the poses it has seen in memory and answers ``/trajectory`` from them; a restarted gateway has
seen nothing. The mapstore already holds the durable state of a stream, so it also subscribes to the ``pose``
topic and keeps each frame's latest pose (a mapped revision is never replaced by a later tracking pose), and
answers ``map/trajectory`` with all of them. Poses come at frame rate and in bursts of revisions: they are
gathered in memory on the Zenoh thread and written in one transaction per flush, from the service loop about
twice a second and before every ``trajectory`` answer, so the database lags the bus by at most one flush (a
kill loses at most that, and ba sends every pose again at the end of the stream)."""
from __future__ import annotations

import threading
import time

import numpy as np

from ..common.schema import Poses
from .store import MapStore

FLUSH_S = 0.5


class PoseLog:
    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._pending: dict[int, tuple[int, np.ndarray, bool]] = {}  # seq -> (t_ns, pose, mapped)
        self._last_flush = time.monotonic()

    def add(self, msg: Poses) -> None:
        """A ``pose`` message (Zenoh thread)."""
        mapped = not msg.tracked
        with self._lock:
            for seq, stamp, pose in zip(msg.frame_seqs.tolist(), msg.stamps_ns.tolist(), msg.poses):
                held = self._pending.get(seq)
                if held is None or mapped or not held[2]:
                    self._pending[seq] = (stamp, np.asarray(pose, np.float64), mapped)

    def due(self) -> bool:
        return time.monotonic() - self._last_flush >= FLUSH_S

    def flush(self, store: MapStore) -> int:
        """Write what is pending; the number of frame poses written."""
        with self._lock:
            rows, self._pending = self._pending, {}
            self._last_flush = time.monotonic()
            if rows:  # under the lock: a concurrent flush must not write an older batch after a newer one
                store.put_frame_poses([(s, t, p, m) for s, (t, p, m) in rows.items()])
        return len(rows)
