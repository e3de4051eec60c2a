"""The request ids a map remembers (idempotency), in fixed-size arrays: no Python object per id.

Each applied request id keeps its original ack (to answer a retry with it, and ``verdict``
with its current verdict), its request fingerprint (a retry with another request under the
same id is refused) and its receive time (``--id-ttl-s`` counts from it), oldest first, at
most ``--id-memory`` of them (100,000 by default, held ten minutes). A long-running server
fills that memory during its first 100,000 operations, so its cost per id is what the
server's resident memory grows by until then. Python objects per id (a dict entry, the id
string, the ack) cost 600-900 bytes of RSS each once the allocator's fragmentation is
counted (``benchmarks/soak_memory.py``); here an id costs one row of fixed-size numpy arrays
(about 190 bytes, allocated when first used):

* a ring of ``capacity`` slots in insertion order: receive time, seq, fingerprint, the id's
  hash, and a 128-byte row holding the id and the rest of its ack (a small msgpack array);
  the rare id whose row would be longer (a submap import's frame list) keeps it in a dict;
* an open-addressing hash table (linear probing, twice the capacity) from the id's hash to
  its slot, checked against the stored id, so a hash collision never confuses two ids.

Eviction is oldest first (the TTL and the count bound), which the ring does for free.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import msgpack
import numpy as np

from mcsm import wire

ROW_BYTES = 128
"""Bytes of a slot's row: 2 length bytes, the id, the ack's msgpack array."""
_NO_FP = bytes(16)


def _blob(ack: wire.Ack) -> bytes:
    v = ack.verdict
    verdict = None if v is None else [v.status, v.nis, v.dof, v.threshold, v.reason,
                                      v.stamp_ns]
    out: bytes = msgpack.packb([ack.op, ack.kind, ack.component, list(ack.frames_added),
                                list(ack.frames_removed), verdict])
    return out


def _ack(rid: str, seq: int, blob: bytes) -> wire.Ack:
    op, kind, component, added, removed, v = msgpack.unpackb(blob)
    verdict = None if v is None else wire.Verdict(v[0], v[1], v[2], v[3], v[4], v[5])
    return wire.Ack(rid, seq, op, kind, component, frames_added=tuple(added),
                    frames_removed=tuple(removed), verdict=verdict)


class IdMemory:
    """Request id -> (ack, fingerprint, receive time ns), oldest first, at most ``capacity``
    (a put beyond it forgets the oldest). Not thread-safe (the map's worker owns it)."""

    def __init__(self, capacity: int) -> None:
        self.capacity = c = max(1, int(capacity))
        # np.zeros: pages are mapped when first written, so a small memory costs little
        self._t = np.zeros(c, np.int64)
        self._seq = np.zeros(c, np.int64)
        self._hash = np.zeros(c, np.int64)
        self._fp = np.zeros((c, 16), np.uint8)
        self._live = np.zeros(c, np.bool_)
        self._op = np.zeros(c, np.uint8)  # index into _opnames
        self._opnames: list[str] = []
        self._rows = np.zeros((c, ROW_BYTES), np.uint8)
        self._long: dict[int, tuple[str, bytes]] = {}  # slot -> (id, ack blob) too long
        size = 1
        while size < 2 * c:
            size *= 2
        self._mask = size - 1
        self._table = np.zeros(size, np.int64)  # 0 empty, -1 deleted, n + 1: insertion n
        self._tombs = 0
        self._head = 0  # insertion number of the next put
        self._tail = 0  # the oldest insertion number that may still be live
        self._n = 0

    def __len__(self) -> int:
        return self._n

    def __contains__(self, rid: object) -> bool:
        return isinstance(rid, str) and self._find(rid)[0] >= 0

    # ------------------------------------------------------------------ slots and table
    def _rid_blob(self, s: int) -> tuple[str, bytes]:
        long = self._long.get(s)
        if long is not None:
            return long
        row = self._rows[s]
        rl, al = int(row[0]), int(row[1])
        raw = row[2:2 + rl + al].tobytes()
        return raw[:rl].decode(), raw[rl:]

    def _find(self, rid: str) -> tuple[int, int]:
        """(insertion number, table index) of ``rid``, or (-1, -1)."""
        h = hash(rid)
        i = h & self._mask
        for _ in range(self._mask + 1):
            e = int(self._table[i])
            if e == 0:
                return -1, -1
            if e > 0:
                s = (e - 1) % self.capacity
                if int(self._hash[s]) == h and self._rid_blob(s)[0] == rid:
                    return e - 1, i
            i = (i + 1) & self._mask
        return -1, -1

    def _unlink(self, n: int, i: int) -> None:
        s = n % self.capacity
        self._table[i] = -1
        self._tombs += 1
        self._live[s] = False
        self._long.pop(s, None)
        self._n -= 1
        if self._tombs > (self._mask + 1) // 4:
            self._rebuild()

    def _rebuild(self) -> None:
        """A fresh table from the live slots (drops the deleted markers)."""
        self._table[:] = 0
        self._tombs = 0
        for n in range(self._tail, self._head):
            s = n % self.capacity
            if self._live[s]:
                self._insert(int(self._hash[s]), n)

    def _insert(self, h: int, n: int) -> None:
        i = h & self._mask
        while int(self._table[i]) > 0:
            i = (i + 1) & self._mask
        if int(self._table[i]) < 0:
            self._tombs -= 1
        self._table[i] = n + 1

    def _write(self, s: int, rid: str, blob: bytes) -> None:
        r = rid.encode()
        if len(r) + len(blob) + 2 > ROW_BYTES or len(r) > 255 or len(blob) > 255:
            self._long[s] = (rid, blob)
            return
        self._long.pop(s, None)
        data = bytes((len(r), len(blob))) + r + blob
        self._rows[s, :len(data)] = np.frombuffer(data, np.uint8)

    # ------------------------------------------------------------------ the API
    def get(self, rid: str) -> tuple[wire.Ack, str, int] | None:
        n, _ = self._find(rid)
        if n < 0:
            return None
        s = n % self.capacity
        fpb = self._fp[s].tobytes()
        return (_ack(rid, int(self._seq[s]), self._rid_blob(s)[1]),
                "" if fpb == _NO_FP else fpb.hex(), int(self._t[s]))

    def put(self, rid: str, ack: wire.Ack, fp: str, t_ns: int) -> None:
        """Remember ``rid`` as the newest id (an id already remembered moves to the end; at
        ``capacity`` the oldest is forgotten)."""
        self.pop(rid)
        if self._head - self._tail >= self.capacity:  # the ring is full
            old = self._tail % self.capacity
            if self._live[old]:
                self.pop(self._rid_blob(old)[0])
            self._tail += 1
        n = self._head
        self._head += 1
        s = n % self.capacity
        h = hash(rid)
        self._t[s], self._seq[s], self._hash[s] = int(t_ns), int(ack.seq), h
        self._fp[s] = np.frombuffer(bytes.fromhex(fp) if len(fp) == 32 else _NO_FP, np.uint8)
        self._op[s] = self._opcode(ack.op)
        self._write(s, rid, _blob(ack))
        self._live[s] = True
        self._n += 1
        self._insert(h, n)

    def _opcode(self, op: str) -> int:
        if op not in self._opnames:
            self._opnames.append(op)
        return self._opnames.index(op)

    def update(self, rid: str, ack: wire.Ack) -> None:
        """Replace the ack of a remembered id (its place, fingerprint and time stay)."""
        n, _ = self._find(rid)
        if n >= 0:
            s = n % self.capacity
            self._seq[s] = int(ack.seq)
            self._op[s] = self._opcode(ack.op)
            self._write(s, rid, _blob(ack))

    def pop(self, rid: str) -> None:
        """Forget ``rid`` (if remembered)."""
        n, i = self._find(rid)
        if n >= 0:
            self._unlink(n, i)

    def _skip_dead(self) -> None:
        while self._tail < self._head and not self._live[self._tail % self.capacity]:
            self._tail += 1

    def oldest_time(self) -> int | None:
        """The receive time of the oldest id (None when empty)."""
        self._skip_dead()
        return None if self._n == 0 else int(self._t[self._tail % self.capacity])

    def pop_oldest(self) -> None:
        self._skip_dead()
        if self._n:
            self.pop(self._rid_blob(self._tail % self.capacity)[0])
            self._skip_dead()

    def clear(self) -> None:
        self._table[:] = 0
        self._live[:] = False
        self._long.clear()
        self._tombs = self._n = 0
        self._tail = self._head

    def _slots(self) -> np.ndarray:
        """The live slots, oldest first."""
        order = np.arange(self._tail, self._head, dtype=np.int64) % self.capacity
        return order[self._live[order]]

    def items(self) -> Iterator[tuple[str, tuple[wire.Ack, str, int]]]:
        """(id, (ack, fingerprint, receive time)), oldest first."""
        for s in self._slots().tolist():
            rid, blob = self._rid_blob(s)
            fpb = self._fp[s].tobytes()
            yield rid, (_ack(rid, int(self._seq[s]), blob),
                        "" if fpb == _NO_FP else fpb.hex(), int(self._t[s]))

    def columns(self) -> IdColumns:
        """Every id, oldest first, as columns (what a recorded snapshot holds), built from
        the arrays in blocks: no Python object per id, little memory beyond the result."""
        slots = self._slots()
        id_parts: list[bytes] = []
        lens = np.zeros(slots.size, np.uint16)
        for k0 in range(0, slots.size, 8192):
            block = slots[k0:k0 + 8192]
            rows = self._rows[block]
            rl = rows[:, 0].astype(np.int64)
            lens[k0:k0 + block.size] = rl
            mask = np.arange(ROW_BYTES - 2)[None, :] < rl[:, None]
            data = rows[:, 2:][mask].tobytes()
            if self._long:  # the few ids kept aside: splice them in, in order
                out, at = [], 0
                for j, sl in enumerate(block.tolist()):
                    long = self._long.get(sl)
                    n = int(rl[j])  # (a long entry's row is stale: skipped)
                    if long is None:
                        out.append(data[at:at + n])
                    at += n
                    if long is not None:
                        r = long[0].encode()
                        out.append(r)
                        lens[k0 + j] = len(r)
                data = b"".join(out)
            id_parts.append(data)
        return IdColumns(b"".join(id_parts), lens, self._seq[slots].copy(),
                         list(self._opnames), self._op[slots].copy(),
                         self._fp[slots].tobytes(), self._t[slots].copy())


@dataclass
class IdColumns:
    """Remembered ids as columns, oldest first: the ids' UTF-8 bytes concatenated and their
    lengths, seqs, operation names and each id's index into them, 16-byte fingerprints
    (zeros: unknown), receive times (ns)."""

    ids: bytes
    lens: np.ndarray
    seq: np.ndarray
    op_names: list[str]
    op: np.ndarray
    fp: bytes
    time_ns: np.ndarray

    def rows(self) -> list[list[Any]]:
        """As :meth:`MapState.export_ids` rows ``[id, seq, op, fingerprint, time_ns]``."""
        ends = np.cumsum(self.lens.astype(np.int64))
        starts = ends - self.lens
        out = []
        for k in range(self.lens.size):
            fpb = self.fp[16 * k:16 * k + 16]
            out.append([self.ids[starts[k]:ends[k]].decode(), int(self.seq[k]),
                        self.op_names[int(self.op[k])],
                        "" if fpb == _NO_FP else fpb.hex(), int(self.time_ns[k])])
        return out


__all__ = ["IdMemory", "IdColumns", "ROW_BYTES"]
