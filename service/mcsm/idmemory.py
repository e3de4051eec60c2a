"""The request ids a map remembers (idempotency), compactly: about 250 bytes per id.

Each applied request id keeps its original ack (to answer a retry with it, and ``verdict``
with its current verdict), its request fingerprint (a retry with another request under the
same id is refused) and its receive time (``--id-ttl-s`` counts from it), oldest first, at
most ``--id-memory`` of them. A map that serves 100,000 ids holds them all for ten minutes
by default, so their cost per id is what a long-running server's memory grows by until the
bound is reached: one Python ``bytes`` per id packs all of it (receive time, seq and
fingerprint as fixed fields, the rest of the ack as a small msgpack array), keyed by the id
in a dict, with the insertion order in a deque of the same key strings; the dataclass acks
this replaces cost about 650 bytes per id.
"""

from __future__ import annotations

import struct
from collections import deque
from collections.abc import Iterator

import msgpack

from mcsm import wire

_HEAD = struct.Struct("<qq16s")  # receive time ns, seq, fingerprint (16 bytes; zeros: none)
_NO_FP = bytes(16)


def _pack(ack: wire.Ack, fp: str, t_ns: int) -> bytes:
    v = ack.verdict
    verdict = None if v is None else [v.status, v.nis, v.dof, v.threshold, v.reason,
                                      v.stamp_ns]
    fpb = bytes.fromhex(fp) if len(fp) == 32 else _NO_FP
    rest: bytes = msgpack.packb([ack.op, ack.kind, ack.component, list(ack.frames_added),
                                 list(ack.frames_removed), verdict])
    return _HEAD.pack(int(t_ns), int(ack.seq), fpb) + rest


def _unpack(rid: str, data: bytes) -> tuple[wire.Ack, str, int]:
    t_ns, seq, fpb = _HEAD.unpack_from(data)
    op, kind, component, added, removed, v = msgpack.unpackb(data[_HEAD.size:])
    verdict = None if v is None else wire.Verdict(v[0], v[1], v[2], v[3], v[4], v[5])
    ack = wire.Ack(rid, seq, op, kind, component, frames_added=tuple(added),
                   frames_removed=tuple(removed), verdict=verdict)
    return ack, ("" if fpb == _NO_FP else fpb.hex()), t_ns


class IdMemory:
    """Request id -> (ack, fingerprint, receive time ns), in insertion order (oldest first).

    Not thread-safe (the map's worker owns it)."""

    def __init__(self) -> None:
        self._d: dict[str, bytes] = {}
        self._order: deque[str] = deque()  # insertion order; may hold stale copies of a key
        self._stale: dict[str, int] = {}  # key -> stale copies of it in _order (the oldest)

    def __len__(self) -> int:
        return len(self._d)

    def __contains__(self, rid: object) -> bool:
        return rid in self._d

    def get(self, rid: str) -> tuple[wire.Ack, str, int] | None:
        data = self._d.get(rid)
        return None if data is None else _unpack(rid, data)

    def put(self, rid: str, ack: wire.Ack, fp: str, t_ns: int) -> None:
        """Remember ``rid`` as the newest id (an id already remembered moves to the end)."""
        self.pop(rid)
        self._d[rid] = _pack(ack, fp, t_ns)
        self._order.append(rid)

    def update(self, rid: str, ack: wire.Ack) -> None:
        """Replace the ack of a remembered id (its place, fingerprint and time stay)."""
        data = self._d.get(rid)
        if data is not None:
            _, fp, t_ns = _unpack(rid, data)
            self._d[rid] = _pack(ack, fp, t_ns)

    def pop(self, rid: str) -> None:
        """Forget ``rid`` (if remembered)."""
        if self._d.pop(rid, None) is not None:
            self._stale[rid] = self._stale.get(rid, 0) + 1

    def _trim_head(self) -> None:
        while self._order:
            rid = self._order[0]
            n = self._stale.get(rid, 0)
            if not n:
                return
            self._order.popleft()
            if n == 1:
                del self._stale[rid]
            else:
                self._stale[rid] = n - 1

    def oldest_time(self) -> int | None:
        """The receive time of the oldest id (None when empty)."""
        self._trim_head()
        if not self._order:
            return None
        return int(_HEAD.unpack_from(self._d[self._order[0]])[0])

    def pop_oldest(self) -> None:
        self._trim_head()
        if self._order:
            del self._d[self._order.popleft()]

    def clear(self) -> None:
        self._d.clear()
        self._order.clear()
        self._stale.clear()

    def items(self) -> Iterator[tuple[str, tuple[wire.Ack, str, int]]]:
        """(id, (ack, fingerprint, receive time)), oldest first."""
        stale = dict(self._stale)
        for rid in list(self._order):
            n = stale.get(rid, 0)
            if n:
                stale[rid] = n - 1
                continue
            data = self._d.get(rid)
            if data is not None:
                yield rid, _unpack(rid, data)


__all__ = ["IdMemory"]
