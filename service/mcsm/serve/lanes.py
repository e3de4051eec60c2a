"""The worker's request queue: two lanes, bounded in count and in bytes.

Requests that change a map (updates, removes, imports, retracts) and the server's own tasks
go to the *write* lane, in arrival order: that order is the maps' sequence order. Requests
that only read (``info``, ``query``, ``verdict``, ``submap_export``) go to the *read* lane,
which the worker empties first, between two writes: a small query is answered within one
operation's time however long the write lane is. A read therefore sees every operation
acknowledged before it was sent (the worker applied those already), and may overtake writes
that were queued but not yet acknowledged, as a read sent a moment earlier would have.

Each lane holds at most ``max_items`` requests and ``max_bytes`` bytes of request payload
(each request counts its payload, at least :data:`ITEM_BYTES`); a put beyond either bound
fails at once, and the server answers ``Busy`` (nothing applied; retry later with the same
id). The bound in bytes is what keeps a flood of large requests from exhausting memory: a
queued update costs about three times its payload (Zenoh's copy, the server's copy, the
decoded samples).
"""

from __future__ import annotations

import threading
from collections import deque
from typing import Any

ITEM_BYTES = 256
"""What a request with a tiny (or no) payload counts against the byte bound."""


class Full(Exception):
    """A lane is full: ``what`` ("request queue length" or "request queue bytes"), the value
    it would have reached and the limit."""

    def __init__(self, what: str, value: int, limit: int) -> None:
        super().__init__(f"{what} {value} exceeds {limit}")
        self.what, self.value, self.limit = what, value, limit


class Lanes:
    """A read lane and a write lane in front of one worker (thread-safe)."""

    def __init__(self, max_items: int, max_bytes: int) -> None:
        self.max_items = max(1, int(max_items))
        self.max_bytes = max(1, int(max_bytes))
        self._cv = threading.Condition()
        self._reads: deque[tuple[Any, int]] = deque()
        self._writes: deque[tuple[Any, int]] = deque()
        self._bytes = [0, 0]  # reads, writes

    def put(self, item: Any, nbytes: int = 0, *, read: bool = False,
            force: bool = False) -> None:
        """Queue ``item`` (``nbytes``: its payload) on the read or the write lane.

        Raises
        ------
        Full
            If the lane holds ``max_items`` requests, or would hold more than ``max_bytes``
            (not raised with ``force``: the server's own stop marker).
        """
        cost = max(ITEM_BYTES, int(nbytes))
        lane, k = (self._reads, 0) if read else (self._writes, 1)
        with self._cv:
            if not force:
                if len(lane) >= self.max_items:
                    raise Full("request queue length", len(lane) + 1, self.max_items)
                if self._bytes[k] + cost > self.max_bytes:
                    raise Full("request queue bytes", self._bytes[k] + cost, self.max_bytes)
            lane.append((item, cost))
            self._bytes[k] += cost
            self._cv.notify()

    def get(self, timeout_s: float | None = None) -> Any:
        """The next item: the oldest read if any, else the oldest write. Blocks; ``None``
        after ``timeout_s`` without one."""
        with self._cv:
            if not self._cv.wait_for(lambda: bool(self._reads or self._writes), timeout_s):
                return None
            if self._reads:
                item, cost = self._reads.popleft()
                self._bytes[0] -= cost
            else:
                item, cost = self._writes.popleft()
                self._bytes[1] -= cost
            return item

    def qsize(self) -> int:
        """Requests waiting in both lanes."""
        with self._cv:
            return len(self._reads) + len(self._writes)

    def nbytes(self) -> int:
        """Bytes of the requests waiting in both lanes."""
        with self._cv:
            return self._bytes[0] + self._bytes[1]


__all__ = ["Lanes", "Full", "ITEM_BYTES"]
