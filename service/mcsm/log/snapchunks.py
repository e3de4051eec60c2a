"""Chunked snapshot records: a map's snapshot of any size as a sequence of bounded records.

A ``/mcsm/snapshot`` record used to hold a map's whole state in one msgpack map. At 100,000
frames and N = 1000 that is 5.6 GB: past the 1 GiB a reader read back, and past the 4 GiB that
msgpack can hold in one ``bin``. A snapshot whose encoding is larger than :func:`chunk_bytes`
(64 MiB unless the environment variable ``MCSM_SNAPSHOT_CHUNK_BYTES`` says otherwise) is now
written as:

1. a **header** on ``/mcsm/snapshot`` (``format`` 2): ``map``, ``seq``, ``digest`` (the map's
   ``state_digest``), ``reason`` and ``chunked``: ``{"parts": k, "bytes": total,
   "body_bytes": b, "crc32": c, "chunk_bytes": C}``;
2. ``k`` **parts** on ``/mcsm/snapshot_part``: ``{"map", "seq", "part": i, "data": bin}``,
   each at most ``C`` bytes of one byte stream, in order, nothing else in between.

The stream is the **body** (the msgpack encoding of the format-1 record with every
component's ``edges`` reduced to ``{"dtype", "shape"}``: ids, verdicts, deferral, window,
structure) followed by each component's edges as raw little-endian float64 in ``(M, N, 7)``
order; ``crc32`` is the CRC-32 of the whole stream. A snapshot that fits in one chunk is still
written as one format-1 record, so small maps' files read in older mcsm as before.

Reading (:class:`Assembler`, driven by :class:`mcsm.log.reader.RecordingReader`): the parts are
checked (same map and seq, consecutive numbers, no byte beyond ``bytes``), the edges are
written into their final arrays part by part (peak memory: the map plus one part), and the
stream's length and CRC are checked at the end; the reassembled record is yielded as one
``/mcsm/snapshot`` item shaped like a format-1 record (``state.components[i].edges`` a numpy
array). A snapshot that is incomplete when another record follows raises
:class:`~mcsm.log.topics.RecordingError` naming the file and byte offsets: the records after a
snapshot that cannot be read back are never skipped silently. One that is incomplete at the
end of the file (cut while it was written) is reported (``pending``) and ignored: nothing
after it was lost.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Iterator
from typing import Any

import msgpack
import numpy as np

from mcsm import wire
from mcsm.errors import McsmError
from mcsm.log.topics import TOPIC_SNAPSHOT, TOPIC_SNAPSHOT_PART
from mcsm.map.carry import encode_snapshot

log = logging.getLogger(__name__)

CHUNK_BYTES_ENV = "MCSM_SNAPSHOT_CHUNK_BYTES"
DEFAULT_CHUNK_BYTES = 64 << 20
"""Largest part (and largest single-record snapshot) written: 64 MiB."""
MIN_CHUNK_BYTES = 1024
CHUNKED_FORMAT = 2
"""``format`` of a chunked snapshot's header (a single-record snapshot has format 1)."""
MAX_SNAPSHOT_ARRAY = 1 << 26
"""Longest msgpack array read in a snapshot (its ``order`` and ``frames`` name every frame;
the wire's own limit, 100,000, would refuse a larger map's snapshot)."""

try:
    from zlib_ng import zlib_ng as _zng

    _crc32: Callable[..., int] = _zng.crc32
except ImportError:  # pragma: no cover - zlib-ng is a dependency; the same CRC, slower
    import zlib

    _crc32 = zlib.crc32


class SnapshotError(McsmError):
    """A chunked snapshot cannot be read back (raised as a RecordingError by the reader)."""


def chunk_bytes() -> int:
    """The part size for new snapshots: ``MCSM_SNAPSHOT_CHUNK_BYTES`` or 64 MiB (at least
    :data:`MIN_CHUNK_BYTES`)."""
    raw = os.environ.get(CHUNK_BYTES_ENV, "")
    try:
        n = int(raw) if raw else DEFAULT_CHUNK_BYTES
    except ValueError:
        n = DEFAULT_CHUNK_BYTES
    return max(MIN_CHUNK_BYTES, n)


def is_header(d: dict[str, Any]) -> bool:
    return isinstance(d.get("chunked"), dict)


def _edges_arrays(state: dict[str, Any]) -> list[np.ndarray]:
    return [np.ascontiguousarray(c["edges"], dtype="<f8") for c in state["components"]]


def records(rec: dict[str, Any], limit: int | None = None) -> Iterator[tuple[str, bytes]]:
    """The records (topic, msgpack message with ``v``) that carry the snapshot record ``rec``
    (``rec["state"]`` a raw :meth:`StochasticMap.snapshot`, edges as arrays): one format-1
    record when it fits in ``limit`` bytes (default :func:`chunk_bytes`), else a header and
    its parts. The parts are made one at a time (memory: one part beyond the snapshot)."""
    limit = chunk_bytes() if limit is None else max(MIN_CHUNK_BYTES, int(limit))
    state = rec["state"]
    arrays = _edges_arrays(state)
    if sum(a.nbytes for a in arrays) < limit:
        single = wire.pack({"v": wire.VERSION, **rec, "state": encode_snapshot(state)})
        if len(single) <= limit:
            yield TOPIC_SNAPSHOT, single
            return
        del single
    skeleton = {**state, "components": [
        {**{k: v for k, v in c.items() if k != "edges"},
         "edges": {"dtype": "<f8", "shape": list(a.shape)}}
        for c, a in zip(state["components"], arrays, strict=True)]}
    body = wire.pack({"v": wire.VERSION, **rec, "format": CHUNKED_FORMAT, "state": skeleton})
    views = [memoryview(body)] + [a.reshape(-1).data.cast("B") for a in arrays]
    total = sum(v.nbytes for v in views)
    crc = 0
    for v in views:
        crc = _crc32(v, crc)
    parts = -(-total // limit)
    head = {"v": wire.VERSION, "map": rec["map"], "seq": rec["seq"], "digest": rec["digest"],
            "format": CHUNKED_FORMAT, "reason": rec.get("reason", "periodic"),
            "chunked": {"parts": parts, "bytes": total, "body_bytes": len(body),
                        "crc32": crc, "chunk_bytes": limit}}
    yield TOPIC_SNAPSHOT, wire.pack(head)

    def part(k: int, data: bytes | bytearray) -> tuple[str, bytes]:
        return TOPIC_SNAPSHOT_PART, wire.pack({"v": wire.VERSION, "map": rec["map"],
                                               "seq": rec["seq"], "part": k,
                                               "data": bytes(data)})

    k, buf = 0, bytearray()
    for v in views:
        off = 0
        while off < v.nbytes:
            take = min(limit - len(buf), v.nbytes - off)
            buf += v[off: off + take]
            off += take
            if len(buf) == limit:
                yield part(k, buf)
                k, buf = k + 1, bytearray()
    if buf:
        yield part(k, buf)
        k += 1
    if k != parts:  # pragma: no cover - arithmetic above
        raise SnapshotError(f"wrote {k} parts, announced {parts}")


def unpack_body(data: bytes | bytearray | memoryview) -> dict[str, Any]:
    """Decode a snapshot's msgpack map (a format-1 record or a chunked one's body) with room
    for every frame name (:data:`MAX_SNAPSHOT_ARRAY`).

    Raises
    ------
    McsmError
        If it is not one msgpack map of this protocol version.
    """
    try:
        obj = msgpack.unpackb(data, raw=False, strict_map_key=True, use_list=True,
                              max_bin_len=len(data), max_str_len=64 * 1024,
                              max_array_len=MAX_SNAPSHOT_ARRAY, max_map_len=1 << 20,
                              max_ext_len=0)
    except (ValueError, TypeError, OverflowError, msgpack.UnpackException) as exc:
        raise SnapshotError(f"undecodable snapshot ({type(exc).__name__})") from None
    if not isinstance(obj, dict) or obj.get("v") != wire.VERSION:
        raise SnapshotError("a snapshot that is not a msgpack map of version "
                            f"{wire.VERSION}")
    return obj


class Assembler:
    """Reassembles chunked snapshots from a file's records, in file order.

    ``edges``: whether to keep the edge arrays (True), to check the stream only and leave
    ``{"dtype", "shape"}`` in place of each component's edges (False; ``inspect``, the
    restore's choice of a start), or a function of the header that says which.
    ``size``: the file's size, an upper bound on what a header may announce.
    """

    def __init__(self, path: str, size: int,
                 edges: bool | Callable[[dict[str, Any]], bool] = True) -> None:
        self.path = path
        self.size = size
        self.edges = edges
        self._head: dict[str, Any] | None = None
        self._head_at = 0
        self._keep = True
        self._next = 0
        self._got = 0
        self._crc = 0
        self._body = bytearray()
        self._doc: dict[str, Any] | None = None
        self._arrays: list[np.ndarray] = []
        # the edge arrays in stream order: their bytes (None when not kept) and sizes
        self._targets: list[memoryview | None] = []
        self._sizes: list[int] = []
        self._idx = 0
        self._off = 0

    @property
    def pending(self) -> str | None:
        """What an unfinished snapshot lacks (None when none is being read)."""
        if self._head is None:
            return None
        c = self._head["chunked"]
        return (f"the chunked snapshot of map {self._head.get('map')!r} at seq "
                f"{self._head.get('seq')} (header at byte {self._head_at}) has {self._next} "
                f"of its {c['parts']} parts")

    def _fail(self, why: str) -> SnapshotError:
        self._head = None
        return SnapshotError(why)

    def start(self, head: dict[str, Any], at: int) -> None:
        """A header at byte ``at``.

        Raises
        ------
        SnapshotError
            If a snapshot is still unfinished or the header does not add up.
        """
        if self._head is not None:
            raise self._fail(f"{self.pending}; a new snapshot header follows at byte {at}")
        c = head["chunked"]
        try:
            parts, total, body = int(c["parts"]), int(c["bytes"]), int(c["body_bytes"])
            int(c["crc32"])
        except (KeyError, TypeError, ValueError):
            raise self._fail(f"a chunked snapshot header at byte {at} without parts, bytes, "
                             "body_bytes and crc32") from None
        if not (0 < parts <= total and 0 < body <= total <= self.size):
            raise self._fail(f"a chunked snapshot header at byte {at} announces {parts} "
                             f"parts, {total} bytes ({body} of body) in a file of "
                             f"{self.size} bytes")
        self._head, self._head_at = head, at
        self._keep = bool(self.edges(head) if callable(self.edges) else self.edges)
        self._next = self._got = self._crc = 0
        self._body = bytearray()
        self._doc, self._arrays, self._targets, self._sizes = None, [], [], []
        self._idx = self._off = 0

    def part(self, d: dict[str, Any], at: int) -> dict[str, Any] | None:
        """A part at byte ``at``: the reassembled record once it was the last, else None.

        Raises
        ------
        SnapshotError
            If it belongs to no snapshot, to another one, comes out of order, or the
            stream does not add up.
        """
        h = self._head
        if h is None:
            raise SnapshotError(f"a snapshot part at byte {at} without its header")
        c = h["chunked"]
        data = d.get("data")
        if (d.get("map") != h.get("map") or d.get("seq") != h.get("seq")
                or d.get("part") != self._next or not isinstance(data, bytes)):
            raise self._fail(f"{self.pending}; the record at byte {at} is part "
                             f"{d.get('part')} of map {d.get('map')!r} at seq "
                             f"{d.get('seq')}")
        total, body_len = int(c["bytes"]), int(c["body_bytes"])
        if self._got + len(data) > total:
            raise self._fail(f"{self.pending}; part {self._next} at byte {at} runs past the "
                             f"{total} bytes announced")
        self._crc = _crc32(data, self._crc)
        mv = memoryview(data)
        if self._got < body_len:
            take = min(body_len - self._got, len(data))
            self._body += mv[:take]
            mv = mv[take:]
            self._got += take
            if self._got == body_len:
                self._open_body(total - body_len, at)
        while mv.nbytes:
            if self._idx >= len(self._sizes):
                raise self._fail(f"{self.pending}; part {self._next} at byte {at} holds "
                                 "more than the body's edges")
            size, off = self._sizes[self._idx], self._off
            take = min(size - off, mv.nbytes)
            target = self._targets[self._idx]
            if target is not None:
                target[off: off + take] = mv[:take]
            self._off += take
            if self._off == size:
                self._idx, self._off = self._idx + 1, 0
            mv = mv[take:]
            self._got += take
        self._next += 1
        if self._next < int(c["parts"]):
            return None
        if self._got != total or self._idx != len(self._sizes):
            raise self._fail(f"{self.pending}; the parts hold {self._got} of the {total} "
                             "bytes announced")
        if self._crc != int(c["crc32"]):
            raise self._fail(f"{self.pending}; the stream's CRC-32 does not match")
        doc = self._doc
        assert doc is not None
        comps = doc["state"]["components"]
        if self._keep:
            for comp, arr in zip(comps, self._arrays, strict=True):
                comp["edges"] = arr
        self._head = None
        out = {**doc, "chunked": dict(c)}
        self._doc, self._arrays, self._targets, self._sizes = None, [], [], []
        return out

    def _open_body(self, edge_bytes: int, at: int) -> None:
        try:
            doc = unpack_body(self._body)
            comps = doc["state"]["components"]
            shapes = [tuple(int(s) for s in c["edges"]["shape"]) for c in comps]
        except (McsmError, KeyError, TypeError, ValueError) as exc:
            raise self._fail(f"{self.pending}; its body (through the part at byte {at}) "
                             f"does not decode: {exc}") from None
        need = sum(8 * int(np.prod(s, dtype=np.int64)) for s in shapes)
        if need != edge_bytes or any(len(s) != 3 or min(s) < 0 for s in shapes):
            raise self._fail(f"{self.pending}; its components' edges {shapes} do not fill "
                             f"the {edge_bytes} bytes after the body")
        self._doc, self._body = doc, bytearray()
        for s in shapes:
            n = 8 * int(np.prod(s, dtype=np.int64))
            target = None
            if self._keep:
                arr = np.empty(s, dtype="<f8")
                self._arrays.append(arr)
                target = arr.reshape(-1).data.cast("B")
            if n:
                self._targets.append(target)
                self._sizes.append(n)
