"""The MCAP bytes of a recording as written: the one-chunk-per-input writer and the writers of
the other layouts (:data:`~mcsm.log.topics.LAYOUTS`).

:class:`ChunkPerInputWriter` ends a chunk (with its message index and CRCs) at every input, so
that each acknowledged input is a complete chunk in the file when the call returns; it writes
the summary and footer itself on a clean close. :func:`new_writer` picks the writer for a
layout; :func:`trim_heap` hands freed heap pages back to the OS after a snapshot.
"""

from __future__ import annotations

import logging
import os
import struct
import tempfile
import zlib
from collections import Counter
from collections.abc import Callable
from typing import Any, BinaryIO

import lz4.frame as lz4_frame
from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (
    Channel,
    DataEnd,
    Header,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)
from mcap.writer import CompressionType, Writer

from mcsm.log.topics import MCAP_MAGIC

log = logging.getLogger(__name__)

_OP_LEN = struct.Struct("<BQ")
_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")
_RECORD_22 = struct.Struct("<BQHIQQ")  # a message's head, or a one-entry message index
_CHUNK_FIELDS = struct.Struct("<QQQII")  # start, end, uncompressed size and CRC, len(compr.)
# a chunk index record up to its compression string: opcode, length, start and end times,
# chunk offset and length, one message index offset (byte count, channel, offset), message
# index length, compression string length
_CHUNK_INDEX_HEAD = struct.Struct("<BQQQQQIHQQI")
#: lz4 "fast acceleration" 2: about half the CPU time of level 0 for nearly the same ratio on
#: planar samples (benchmarks/recording_size.py); any lz4 frame decoder reads it
_LZ4_LEVEL = -2
# zlib-ng's CRC-32 is the same function as zlib's, about 4x faster here, and can combine CRCs
_crc32: Callable[..., int] = zlib.crc32
_crc32_combine: Callable[[int, int, int], int] | None = None
try:
    from zlib_ng import zlib_ng as _zng

    _crc32, _crc32_combine = _zng.crc32, _zng.crc32_combine
except ImportError:  # pragma: no cover - zlib-ng is a dependency; the same CRCs, only slower
    pass


def new_writer(fh: BinaryIO, layout: str, library: str,
                spill_dir: str | os.PathLike[str] | None = None) -> Any:
    """A started writer for ``layout`` (see :data:`LAYOUTS`)."""
    if layout in ("indexed", "indexed-lz4"):
        return ChunkPerInputWriter(fh, lz4=layout == "indexed-lz4", library=library,
                                   spill_dir=spill_dir)
    if layout == "flat":
        w = Writer(fh, use_chunking=False, enable_crcs=True)
    else:
        w = Writer(fh, use_chunking=True, compression=CompressionType.ZSTD, enable_crcs=True,
                   enable_data_crcs=True)
    w.start(profile="", library=library)
    return w


class ChunkPerInputWriter:
    """The recorder's MCAP writer: each message in its own chunk, on disk when the call returns.

    The same file as ``mcap.writer.Writer(use_chunking=True, enable_crcs=True,
    enable_data_crcs=True)`` with ``flush()`` after every message (mcap's readers, seeking and
    streaming, read it; tests check that), built for the acknowledgement path: one pass of
    CRC-32 over a message (zlib-ng's, about 4x zlib's; the data-section CRC is combined, not
    recomputed), one ``writev`` system call per message with no copy of the sample bytes, and
    lz4 only where it pays. Schema, channel and metadata records are written outside chunks,
    before the messages that use them; :meth:`finish` writes the summary (schemas, channels,
    statistics, chunk and metadata indexes, summary offsets) and the footer.

    With ``lz4``, a chunk is stored lz4-compressed when that saves at least 10 %; a channel
    whose messages do not compress (3-D samples are noise in their low bytes) is stored as it
    is and tried again every :attr:`LZ4_RETRY` messages, so it costs next to nothing.
    """

    LZ4_RETRY = 64
    #: bytes of chunk index records kept in memory before they go to the spill file
    SPILL_BYTES = 256 * 1024

    def __init__(self, fh: BinaryIO, *, lz4: bool, library: str,
                 spill_dir: str | os.PathLike[str] | None = None) -> None:
        self._fd = fh.fileno()
        self._lz4 = lz4
        self._pos = 0
        self._crc = 0  # data section CRC so far
        self._schemas: dict[int, Schema] = {}
        self._channels: dict[int, Channel] = {}
        # The summary needs one chunk index per chunk (one per input). They are packed as
        # records into a small buffer and spilled to an unlinked temporary file beside the
        # recording, so a long recording costs no memory per input; finish() copies them.
        self._ci_buf = bytearray()
        self._ci_spill: BinaryIO | None = None
        self._ci_bytes = 0
        self._n_chunks = 0
        self._spill_dir = spill_dir
        self.failed = False  # a write failed: the file ends after its last complete record
        self._metadata_indexes: list[MetadataIndex] = []
        self._counts: Counter[int] = Counter()
        self._skip_lz4: dict[int, int] = {}
        self._t0: int | None = None
        self._t1 = 0
        self._write([MCAP_MAGIC])
        self._record(Header(profile="", library=library))

    def _write(self, parts: list[bytes], crcs: list[int | None] | None = None) -> None:
        """Append ``parts`` with one system call; ``crcs`` may give parts' own CRC-32.

        Raises
        ------
        OSError
            If the write fails (full disk, I/O error): the file is cut back to its last
            complete record first, and every later write is refused.
        """
        if self.failed:
            raise OSError("the recording failed earlier; nothing more is written")
        crc = self._crc
        total = 0
        for k, part in enumerate(parts):
            known = crcs[k] if crcs is not None else None
            if known is not None and _crc32_combine is not None:
                crc = _crc32_combine(crc, known, len(part))
            else:
                crc = _crc32(part, crc)
            total += len(part)
        self._write_raw(parts, total)
        self._crc = crc
        self._pos += total

    def _write_raw(self, parts: list[bytes], total: int) -> None:
        try:
            _write_all(self._fd, parts, total)
        except OSError:
            self._fail()
            raise

    def _fail(self) -> None:
        """A write failed: cut the file back to its last complete record (so that it reads
        as cut, never as damaged) and refuse every later write."""
        self.failed = True
        try:
            os.ftruncate(self._fd, self._pos)
        except OSError as exc:
            log.error("could not cut the recording back to byte %d: %s", self._pos, exc)

    def _record(self, rec: Any) -> int:
        rb = RecordBuilder()
        rec.write(rb)
        data = rb.end()
        self._write([data])
        return len(data)

    def register_schema(self, name: str, encoding: str, data: bytes) -> int:
        sid = len(self._schemas) + 1
        self._schemas[sid] = Schema(id=sid, name=name, encoding=encoding, data=data)
        self._record(self._schemas[sid])
        return sid

    def register_channel(self, topic: str, message_encoding: str, schema_id: int,
                         metadata: dict[str, str] | None = None) -> int:
        cid = len(self._channels) + 1
        self._channels[cid] = Channel(id=cid, topic=topic, message_encoding=message_encoding,
                                      schema_id=schema_id, metadata=dict(metadata or {}))
        self._record(self._channels[cid])
        return cid

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        offset = self._pos
        length = self._record(Metadata(name=name, metadata=dict(data)))
        self._metadata_indexes.append(MetadataIndex(offset=offset, length=length, name=name))

    def add_message(self, channel_id: int, log_time: int, data: bytes, publish_time: int,
                    sequence: int = 0) -> None:
        """Write ``data`` as the only message of a new chunk, followed by its message index."""
        head = _RECORD_22.pack(0x05, 22 + len(data), channel_id, sequence, log_time,
                               publish_time)
        size = len(head) + len(data)
        head_crc, data_crc = _crc32(head), _crc32(data)
        records_crc = (_crc32_combine(head_crc, data_crc, len(data))
                       if _crc32_combine is not None else _crc32(data, head_crc))
        packed = b""
        if self._lz4:
            skip = self._skip_lz4.get(channel_id, 0)
            if skip:
                self._skip_lz4[channel_id] = skip - 1
            else:
                packed = lz4_frame.compress(head + data, compression_level=_LZ4_LEVEL)
                if len(packed) > 0.9 * size:
                    packed = b""
                    self._skip_lz4[channel_id] = self.LZ4_RETRY
        compression = b"lz4" if packed else b""
        stored = len(packed) if packed else size
        chunk_len = _CHUNK_FIELDS.size + len(compression) + 8 + stored
        chunk_head = b"".join((_OP_LEN.pack(0x06, chunk_len),
                               _CHUNK_FIELDS.pack(log_time, log_time, size, records_crc,
                                                  len(compression)),
                               compression, _U64.pack(stored)))
        index = _RECORD_22.pack(0x07, 22, channel_id, 16, log_time, 0)
        start = self._pos
        if packed:
            self._write([chunk_head, packed, index])
        else:
            self._write([chunk_head, head, data, index], [None, head_crc, data_crc, None])
        self._chunk_index(_CHUNK_INDEX_HEAD.pack(
            0x08, 8 * 4 + 4 + 10 + 8 + 4 + len(compression) + 16, log_time, log_time, start,
            9 + chunk_len, 10, channel_id, start + 9 + chunk_len, len(index),
            len(compression)) + compression + _U64.pack(stored) + _U64.pack(size))
        self._counts[channel_id] += 1
        self._t0 = log_time if self._t0 is None else min(self._t0, log_time)
        self._t1 = max(self._t1, log_time)

    def flush(self) -> None:
        """Nothing to do: every record reached the OS when the call that wrote it returned."""

    def _chunk_index(self, rec: bytes) -> None:
        """Keep one packed chunk index record for the summary (spilled beyond SPILL_BYTES)."""
        self._ci_buf += rec
        self._ci_bytes += len(rec)
        self._n_chunks += 1
        if len(self._ci_buf) >= self.SPILL_BYTES:
            self._spill()

    def _spill(self) -> None:
        if self._ci_spill is None:
            self._ci_spill = tempfile.TemporaryFile(  # noqa: SIM115 - closed in finish/close
                prefix=".mcsm-chunk-index-", dir=self._spill_dir, buffering=0)
        try:
            self._ci_spill.write(self._ci_buf)
        except OSError:
            self._fail()
            raise
        self._ci_buf.clear()

    def close_spill(self) -> None:
        """Drop the spilled chunk indexes (after finish, or when the file is abandoned)."""
        if self._ci_spill is not None:
            self._ci_spill.close()
            self._ci_spill = None
        self._ci_buf.clear()

    def finish(self) -> None:
        """Write the data end record, the summary and the footer. The chunk indexes are
        copied from the spill file block by block, so closing costs no memory per input.

        Raises
        ------
        OSError
            If a write fails: the file is cut back to its end before the data end record (so
            it reads as cut, as after a SIGKILL; ``mcsm recover`` indexes it).
        """
        data_end = self._pos
        try:
            self._finish()
        except OSError:
            self._pos = data_end
            self._fail()
            raise
        finally:
            self.close_spill()

    def _finish(self) -> None:
        self._record(DataEnd(data_section_crc=self._crc))
        summary_start = self._pos
        offsets: list[SummaryOffset] = []
        crc = 0
        pos = summary_start

        def out(data: bytes) -> None:
            nonlocal crc, pos
            crc = _crc32(data, crc)
            self._write_raw([data], len(data))
            pos += len(data)

        def group(opcode: int, records: list[Any]) -> None:
            if not records:  # no offset for an empty group (readers flag one as an error)
                return
            rb = RecordBuilder()
            for r in records:
                r.write(rb)
            data = rb.end()
            offsets.append(SummaryOffset(group_opcode=opcode, group_start=pos,
                                         group_length=len(data)))
            out(data)

        group(Opcode.SCHEMA, list(self._schemas.values()))
        group(Opcode.CHANNEL, list(self._channels.values()))
        group(Opcode.STATISTICS, [Statistics(
            attachment_count=0, channel_count=len(self._channels),
            channel_message_counts=dict(self._counts), chunk_count=self._n_chunks,
            message_count=sum(self._counts.values()), message_start_time=self._t0 or 0,
            message_end_time=self._t1, metadata_count=len(self._metadata_indexes),
            schema_count=len(self._schemas))])
        if self._ci_bytes:
            offsets.append(SummaryOffset(group_opcode=Opcode.CHUNK_INDEX, group_start=pos,
                                         group_length=self._ci_bytes))
            if self._ci_spill is not None:
                self._ci_spill.seek(0)
                while True:
                    block = self._ci_spill.read(1 << 20)
                    if not block:
                        break
                    out(block)
            out(bytes(self._ci_buf))
        group(Opcode.METADATA_INDEX, list(self._metadata_indexes))
        summary_offset_start = pos
        rb = RecordBuilder()
        for o in offsets:
            o.write(rb)
        out(rb.end())
        footer = struct.pack("<BQQQ", Opcode.FOOTER, 20, summary_start, summary_offset_start)
        footer += _U32.pack(_crc32(footer, crc))
        self._write_raw([footer, MCAP_MAGIC], len(footer) + len(MCAP_MAGIC))


def _write_all(fd: int, parts: list[bytes], total: int) -> None:
    done = os.writev(fd, parts)
    if done < total:  # a short write (rare): finish it the slow way
        rest = memoryview(b"".join(parts))[done:]
        while rest:
            rest = rest[os.write(fd, rest):]


def _load_trim() -> Callable[[], None]:
    """glibc's ``malloc_trim(0)``, or a no-op elsewhere."""
    try:
        import ctypes

        fn = ctypes.CDLL("libc.so.6").malloc_trim
    except (OSError, AttributeError):
        return lambda: None

    def trim() -> None:
        fn(0)

    return trim


trim_heap = _load_trim()
"""Hand the heap's free pages back to the OS. A snapshot record is written through a few
transient buffers of its whole size (tens of MB with 100,000 remembered ids); glibc keeps
those pages after they are freed, so without this a server's resident memory ratchets up
with the largest snapshot written (about 20 MB in benchmarks/soak_memory.py). Called after
each snapshot (every --disk-snapshot-every operations): about a millisecond."""
