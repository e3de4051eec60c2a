"""Reading a recording: :class:`RecordingReader` streams the records of a complete, cut or
damaged file (checking every CRC; chunked snapshots reassembled by :func:`items`), and
:func:`scan_chunks` finds the intact chunks after a damaged one (for :func:`mcsm.log.recover`).
"""

from __future__ import annotations

import logging
import mmap
import os
import struct
import time
import zlib
from collections.abc import Callable, Iterator
from io import BytesIO
from pathlib import Path
from typing import Any

from mcap.exceptions import EndOfFile, McapError, RecordLengthLimitExceeded
from mcap.records import (
    Channel,
    Chunk,
    DataEnd,
    Footer,
    Message,
    Metadata,
    Schema,
)
from mcap.stream_reader import StreamReader, breakup_chunk

from mcsm import wire
from mcsm.errors import McsmError
from mcsm.log.snapchunks import Assembler, SnapshotError, is_header, unpack_body
from mcsm.log.topics import (
    FORMAT_VERSION,
    LEGACY_ARITHMETIC_VERSION,
    MAX_RECORD_BYTES,
    MCAP_MAGIC,
    TOPIC_SNAPSHOT,
    TOPIC_SNAPSHOT_PART,
    RecordingError,
    RecordItem,
)

log = logging.getLogger(__name__)

_STREAM_ERRORS = (McapError, EOFError, ValueError, struct.error, KeyError, IndexError,
                  UnicodeDecodeError)


def _ends_with_footer(path: Path, size: int) -> bool:
    if size < 2 * len(MCAP_MAGIC) + 29:
        return False
    with open(path, "rb") as fh:
        fh.seek(size - len(MCAP_MAGIC))
        return fh.read(len(MCAP_MAGIC)) == MCAP_MAGIC


def _summary_crc_ok(path: Path, size: int, footer: Footer) -> bool:
    """Check the footer's summary CRC (MCAP spec: summary start .. summary_offset_start)."""
    footer_start = size - len(MCAP_MAGIC) - 29
    start = footer.summary_start or footer_start
    if not 0 < start <= footer_start:
        return False
    crc = 0
    with open(path, "rb") as fh:
        fh.seek(start)
        remaining = size - len(MCAP_MAGIC) - 4 - start
        while remaining > 0:
            block = fh.read(min(remaining, 1 << 20))
            if not block:
                return False
            crc = zlib.crc32(block, crc)
            remaining -= len(block)
    return crc == footer.summary_crc


class RecordingReader:
    """Stream the records of a recording, complete, cut short (SIGKILL, full disk) or damaged.

    Iterating yields :class:`RecordItem` in file order and checks every CRC the file has (each
    chunk, the data section, the summary). Afterwards: ``complete`` (a footer was read and
    every CRC matched), ``cut`` (the file ends before its footer), ``damage`` (why a damaged
    file could not be read further: a CRC mismatch, an undecodable record), ``tail_error``
    (why reading stopped early, either way) and ``stop_offset`` (the byte where it stopped).
    Reading stops at the first cut or damage; every record before it is yielded.

    A chunked snapshot (:mod:`mcsm.log.snapchunks`) is yielded as one ``/mcsm/snapshot`` item once
    its last part was read; ``edges`` (a bool, or a function of its header) says whether its
    edge arrays are kept or only checked. ``pending_snapshot`` says what an unfinished one at
    the end of the file lacks (a file cut while it was written; nothing after it was lost).

    Raises
    ------
    RecordingError
        If the file is not an MCAP file (no magic and header); while iterating, if a
        snapshot cannot be read back (an unfinished chunked snapshot followed by another
        record, or a record larger than :data:`MAX_RECORD_BYTES`): the message names the
        file and the byte offsets, and the records after it are not read.
    OSError
        If the file cannot be opened.
    """

    def __init__(self, path: str | os.PathLike[str],
                 progress: Callable[[int, int], None] | None = None,
                 edges: bool | Callable[[dict[str, Any]], bool] = True) -> None:
        self.path = Path(path)
        self.edges = edges
        self.record_offset = 0  # where the record last yielded by raw() starts (its chunk)
        self.oversize: str | None = None
        self.pending_snapshot: str | None = None
        self.size = self.path.stat().st_size
        self.progress = progress
        self.complete = False
        self.tail_error: str | None = None
        self.damage: str | None = None
        self.stop_offset = 0
        self.library = ""
        self.metadata: dict[str, dict[str, str]] = {}
        self.n_messages = 0
        self.n_chunks = 0
        self.n_chunks_crc = 0
        self.data_crc = False  # the data section CRC was present and matched
        self.summary_crc = False  # the summary CRC was present and matched
        self.channels: dict[int, Channel] = {}
        self.schemas: dict[int, Schema] = {}

    @property
    def cut(self) -> bool:
        """The file ends before its footer (and shows no other damage)."""
        return not self.complete and self.damage is None and self.tail_error is not None

    @property
    def layout(self) -> str:
        """"indexed" (chunks; format 2), "flat" (no chunks; format 1) or "empty" (no records)."""
        fmt = self.metadata.get("mcsm", {}).get("format", "")
        if self.n_chunks or fmt.endswith(f"v{FORMAT_VERSION}"):
            return "indexed"
        return "flat" if self.n_messages else "empty"

    @property
    def arithmetic_version(self) -> int:
        """The ``mcsm`` metadata's arithmetic version (1 for files that do not say); known
        once iteration has read the metadata record, at the file's start."""
        try:
            return int(self.metadata.get("mcsm", {}).get("arithmetic_version",
                                                          LEGACY_ARITHMETIC_VERSION))
        except ValueError:
            return LEGACY_ARITHMETIC_VERSION

    def _stopped(self, exc: BaseException, at: int, what: str = "") -> None:
        self.stop_offset = at
        eof = isinstance(exc, (EndOfFile, EOFError, struct.error))
        if isinstance(exc, RecordLengthLimitExceeded):
            self.oversize = (f"the record at byte {at} is longer than the "
                             f"{MAX_RECORD_BYTES} bytes read back ({exc}); the records after "
                             "it are not read")
        if eof:
            self.tail_error = (f"the file ends inside the record at byte {at} of {self.size}"
                               if at < self.size else f"the file ends at byte {self.size}")
        else:
            self.tail_error = f"{what or type(exc).__name__} at byte {at} of {self.size}: {exc}"
        if not eof or _ends_with_footer(self.path, self.size):
            self.damage = self.tail_error

    def raw(self) -> Iterator[Schema | Channel | Message | Metadata]:
        """The file's schema, channel, metadata and message records, CRCs checked."""
        with open(self.path, "rb") as fh:
            reader = StreamReader(fh, emit_chunks=True, validate_crcs=True,
                                  record_size_limit=MAX_RECORD_BYTES)
            records = iter(reader.records)
            last_report = 0.0
            try:
                header = next(records)
            except (*_STREAM_ERRORS, StopIteration) as exc:
                raise RecordingError(str(self.path), f"not an MCAP file ({type(exc).__name__})"
                                     ) from None
            self.library = str(getattr(header, "library", ""))
            while True:
                pos = fh.tell()
                try:
                    rec = next(records)
                except StopIteration:
                    break
                except _STREAM_ERRORS as exc:
                    self._stopped(exc, pos)
                    break
                inner: list[Any] = [rec]
                self.record_offset = pos
                if isinstance(rec, Chunk):
                    self.n_chunks += 1
                    self.n_chunks_crc += rec.uncompressed_crc != 0
                    try:
                        inner = list(breakup_chunk(rec, validate_crc=True))
                    except _STREAM_ERRORS as exc:
                        self._stopped(exc, pos, "bad chunk")
                        self.damage = self.tail_error
                        break
                for r in inner:
                    if isinstance(r, Schema):
                        self.schemas[r.id] = r
                        yield r
                    elif isinstance(r, Channel):
                        self.channels[r.id] = r
                        yield r
                    elif isinstance(r, Metadata):
                        self.metadata[r.name] = dict(r.metadata)
                        yield r
                    elif isinstance(r, Message):
                        if r.channel_id not in self.channels:
                            self.stop_offset = pos
                            self.tail_error = self.damage = (
                                f"message on undeclared channel {r.channel_id} at byte {pos}")
                            return
                        self.n_messages += 1
                        yield r
                    elif isinstance(r, DataEnd):
                        self.data_crc = r.data_section_crc != 0
                    elif isinstance(r, Footer):
                        self.stop_offset = self.size
                        if r.summary_crc != 0:
                            if not _summary_crc_ok(self.path, self.size, r):
                                self.tail_error = self.damage = "summary CRC mismatch"
                                return
                            self.summary_crc = True
                        self.complete = True
                        return
                if self.progress is not None:
                    now = time.monotonic()
                    if now - last_report > 0.1:
                        last_report = now
                        self.progress(fh.tell(), self.size)
            if self.progress is not None:
                self.progress(self.size if self.complete else fh.tell(), self.size)

    def __iter__(self) -> Iterator[RecordItem]:
        """The decoded messages; chunked snapshots reassembled (:func:`items`)."""
        return items(self)


def scan_chunks(path: str | os.PathLike[str], start: int) -> Iterator[tuple[int, list[Any]]]:
    """Find the intact chunks after byte ``start`` of a damaged file (their CRCs match).

    Yields (offset, records of the chunk). Used by :func:`recover` to save what follows a
    damaged chunk; a flat (unchunked) file has nothing to find this way.
    """
    p = Path(path)
    size = p.stat().st_size
    if size <= start:
        return
    with open(p, "rb") as fh, mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as mm:
        i = start
        while i < size:
            j = mm.find(b"\x06", i)
            if j < 0 or j + 9 > size:
                return
            (length,) = struct.unpack_from("<Q", mm, j + 1)
            if not 36 <= length <= min(MAX_RECORD_BYTES, size - j - 9):
                i = j + 1
                continue
            try:
                chunk = Chunk.read(_ReadStream(mm[j + 9: j + 9 + length]))
                if chunk.uncompressed_crc == 0 or chunk.compression not in ("", "zstd", "lz4"):
                    raise ValueError("not a chunk with a CRC")
                records = list(breakup_chunk(chunk, validate_crc=True))
            except _STREAM_ERRORS:
                i = j + 1
                continue
            yield j, records
            i = j + 9 + length


def _ReadStream(data: bytes) -> Any:  # noqa: N802 - a constructor-like helper
    from mcap.data_stream import ReadDataStream

    return ReadDataStream(BytesIO(data))


def items(reader: RecordingReader) -> Iterator[RecordItem]:
    """:class:`RecordingReader`'s messages, decoded, each chunked snapshot
    yielded once as one ``/mcsm/snapshot`` item (its header's log time); afterwards
    ``reader.pending_snapshot`` says what an unfinished one at the end lacks.

    Raises
    ------
    RecordingError
        If a snapshot cannot be read back with records after it, or a record was longer than
        the reader reads: the records after it are never skipped silently.
    """
    asm = Assembler(str(reader.path), reader.size, reader.edges)
    head_time = 0
    for rec in reader.raw():
        if not isinstance(rec, Message):
            continue
        topic = reader.channels[rec.channel_id].topic
        at = reader.record_offset
        try:
            if topic in (TOPIC_SNAPSHOT, TOPIC_SNAPSHOT_PART):
                data = unpack_body(rec.data)
            else:
                data = wire.unpack(rec.data, max_bytes=MAX_RECORD_BYTES)
        except McsmError as exc:
            reader.tail_error = reader.damage = f"undecodable record on {topic}: {exc}"
            return
        try:
            if topic == TOPIC_SNAPSHOT_PART:
                whole = asm.part(data, at)
                if whole is not None:
                    yield RecordItem(TOPIC_SNAPSHOT, whole, head_time)
                continue
            if asm.pending is not None:
                raise SnapshotError(f"{asm.pending}; the record at byte {at} ({topic}) "
                                    "follows: the snapshot cannot be read back")
            if topic == TOPIC_SNAPSHOT and is_header(data):
                asm.start(data, at)
                head_time = int(rec.log_time)
                continue
        except SnapshotError as exc:
            raise RecordingError(str(reader.path), f"{exc}; the records after it are not "
                                    "read (mcsm recover cannot mend a snapshot)") from None
        yield RecordItem(topic, data, int(rec.log_time))
    reader.pending_snapshot = asm.pending
    if reader.oversize is not None:
        raise RecordingError(str(reader.path), reader.oversize)
    if reader.pending_snapshot is not None:
        note = f"{reader.pending_snapshot} (the file ends inside it)"
        reader.tail_error = note if reader.tail_error is None else f"{reader.tail_error}; {note}"
        log.warning("%s: %s", reader.path, note)
