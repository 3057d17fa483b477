"""The mapstore's cache of recent query findings, per scoring index (one map revision under one basis)."""
from __future__ import annotations

from collections import OrderedDict


class AnswerCache:
    """What recent query vectors found (``services.mapstore.queries``) on one scoring index. An index lives for one
    map revision under one basis, so a finding is never reused on a map it was not computed on. Used under the
    map state's lock."""

    def __init__(self, capacity: int):
        self.capacity = capacity
        self._index: object | None = None
        self._found: OrderedDict[tuple, object] = OrderedDict()

    def get(self, index, key: tuple | None):
        if key is None or index is not self._index or key not in self._found:
            return None
        self._found.move_to_end(key)
        return self._found[key]

    def put(self, index, key: tuple | None, found) -> None:
        if key is None or self.capacity <= 0:
            return
        if index is not self._index:  # a new map revision or basis: what was found before is stale
            self._index = index
            self._found.clear()
        self._found[key] = found
        while len(self._found) > self.capacity:
            self._found.popitem(last=False)
