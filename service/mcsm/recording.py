"""MCAP recording of every accepted input, and deterministic replay.

A recording is a chunked, indexed MCAP file (lz4 chunk compression) with CRCs (chunk and data
section) and a summary when it was closed cleanly. The server calls :meth:`Recorder.input`
before it acknowledges; that call ends the open chunk (``Writer.flush()``), so every
acknowledged input is in the file as a complete chunk with its message index: a SIGKILL loses
nothing acknowledged, and ``mcsm recover`` turns the cut file into a clean indexed one.
Message encoding ``msgpack``; one channel per kind of record, each with a ``jsonschema``
schema record (each schema once) embedding the schema from ``schemas/``:

==========================  ===================================================================
topic                       message
==========================  ===================================================================
``/mcsm/config``            ``record_config``: a map's name, options and arithmetic version
``/mcsm/in/update``         ``record_input``: update or point update, exact request bytes
``/mcsm/in/remove``         ``record_input``: remove
``/mcsm/in/submap_import``  ``record_input``: submap import
``/mcsm/in/retract``        ``record_input``: retract (``/mcsm/in/reinstate``: reinstate)
``/mcsm/checkpoint``        ``record_checkpoint``: state digest after operation ``seq``
``/mcsm/snapshot``          ``record_snapshot``: the whole state of a map after ``seq``
==========================  ===================================================================

The input topics are the table's (:data:`mcsm.ops.INPUT_TOPICS`). Each input carries the map's
sequence number (also the MCAP ``sequence``), the receive time (the MCAP ``publish_time``;
``log_time`` is when the record was written, never earlier), the sender and the request id.
Queries and exports change nothing and are not recorded; rejected inputs are not recorded. A
metadata record ``mcsm`` names the software and the core's arithmetic version
(:data:`mcsm.core.ARITHMETIC_VERSION`); recordings without it were made by arithmetic version
1.

Replay (:func:`replay`) reads the file with mcap's ``StreamReader`` only (checking CRCs),
because after a SIGKILL the file has no summary or footer; it decodes each request with
:mod:`mcsm.wire`, applies it through :class:`MapState` (the same code the live server runs) and
checks every checkpoint.
"""

from __future__ import annotations

import logging
import mmap
import os
import struct
import sys
import tempfile
import time
import uuid
import zlib
from collections import Counter
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from importlib import resources
from io import BytesIO
from pathlib import Path
from typing import Any, BinaryIO

import lz4.frame as lz4_frame
from mcap.data_stream import RecordBuilder
from mcap.exceptions import EndOfFile, McapError
from mcap.opcode import Opcode
from mcap.records import (
    Channel,
    Chunk,
    DataEnd,
    Footer,
    Header,
    Message,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import CompressionType, Writer

from mcsm import __version__, ops, wire
from mcsm.carry import decode_ids, decode_window, encode_ids, encode_window
from mcsm.carry import decode_snapshot as decode_snapshot  # re-exported (replication)
from mcsm.carry import encode_snapshot as encode_snapshot
from mcsm.core import ARITHMETIC_VERSION
from mcsm.core.smap import StochasticMap
from mcsm.deferral import DeferOptions, DeferState
from mcsm.errors import McsmError
from mcsm.history import DEFAULT_SNAPSHOT_EVERY, DEFAULT_SNAPSHOTS_KEPT
from mcsm.state import DEFAULT_ID_TTL_S, DEFAULT_LRU, MapState

log = logging.getLogger(__name__)

TOPIC_CONFIG = "/mcsm/config"
TOPIC_CHECKPOINT = "/mcsm/checkpoint"
TOPIC_SNAPSHOT = "/mcsm/snapshot"
INPUT_TOPICS = ops.INPUT_TOPICS
"""Recording topic of each state-changing operation (from the table, :mod:`mcsm.ops`)."""
TOPIC_OPS = ops.TOPIC_OPS
_SCHEMAS = {TOPIC_CONFIG: ("mcsm.RecordConfig", "record_config.json"),
            TOPIC_CHECKPOINT: ("mcsm.RecordCheckpoint", "record_checkpoint.json"),
            TOPIC_SNAPSHOT: ("mcsm.RecordSnapshot", "record_snapshot.json"),
            **{t: ("mcsm.RecordInput", "record_input.json") for t in INPUT_TOPICS.values()}}
MAX_RECORD_BYTES = 1 << 30
"""Largest record read back: a state snapshot holds a whole map (M x N x 7 float64)."""
SNAPSHOT_FORMAT = 1
#: version of the file layout, in the ``mcsm`` metadata record ("mcsm recording v2")
FORMAT_VERSION = 2
#: "indexed-lz4" (chunked, indexes, CRCs, lz4 chunk compression; the default), "indexed" (the
#: same uncompressed), "indexed-zstd", or "flat" (the unchunked layout of format 1, kept
#: selectable only so that benchmarks can compare them in one run); docs/recordings.md has the
#: measurements behind the default: lz4 halves planar maps' files and costs ~0.03-0.1 ms/input
LAYOUTS = ("indexed-lz4", "indexed", "indexed-zstd", "flat")
DEFAULT_LAYOUT = "indexed-lz4"
LAYOUT_ENV = "MCSM_RECORDING_LAYOUT"
#: arithmetic version of a recording that does not say (made before the field existed)
LEGACY_ARITHMETIC_VERSION = 1
_MAGIC = b"\x89MCAP0\r\n"
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
_STREAM_ERRORS = (McapError, EOFError, ValueError, struct.error, KeyError, IndexError,
                  UnicodeDecodeError)


class RecordingError(McsmError):
    """A recording cannot be read or written (not MCAP, unknown map, diverging replay)."""

    def __init__(self, path: str, reason: str) -> None:
        super().__init__(f"{path}: {reason}", path=path, reason=reason)


def schema_bytes(filename: str) -> bytes:
    """One JSON Schema of ``schemas/``, read through importlib.resources (works from a wheel)."""
    return resources.files("mcsm.schemas").joinpath(filename).read_bytes()


decode_input = ops.decode_input


# --------------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------------

def _new_writer(fh: BinaryIO, layout: str, library: str,
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
        self._write([_MAGIC])
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
        self._write_raw([footer, _MAGIC], len(footer) + len(_MAGIC))


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


_trim_heap = _load_trim()
"""Hand the heap's free pages back to the OS. A snapshot record is written through a few
transient buffers of its whole size (tens of MB with 100,000 remembered ids); glibc keeps
those pages after they are freed, so without this a server's resident memory ratchets up
with the largest snapshot written (about 20 MB in benchmarks/soak_memory.py). Called after
each snapshot (every --disk-snapshot-every operations): about a millisecond."""


def split_name(base: str | os.PathLike[str], index: int) -> Path:
    """File ``index`` of a split recording whose ``--record`` path is ``base``:
    ``run.mcap`` gives ``run_0000.mcap``, ``run_0001.mcap``, ... (``mcsm serve --split-size``)."""
    b = Path(base)
    return b.with_name(f"{b.stem}_{int(index):04d}{b.suffix or '.mcap'}")


class Recorder:
    """Append-only MCAP writer; every record is flushed to the OS before the call returns.

    Parameters
    ----------
    path : the new file (refused if it exists); with splitting, the base name of the files
        (:func:`split_name`)
    fsync : also ``os.fsync`` after each input (survives power loss; ~4 ms per message here)
    layout : one of :data:`LAYOUTS` (default ``"indexed-lz4"``; ``"flat"`` is format 1, for
        benchmark comparisons only); the environment variable ``MCSM_RECORDING_LAYOUT`` sets
        the default
    split_bytes, split_s : start a new file once the current one holds this many bytes, or
        was opened this many seconds ago (0: never; ``mcsm serve --split-size`` and
        ``--split-duration``). The check follows each input, so a file holds at least one
        input and ends at a clean close; the next file starts with every map's config and a
        snapshot (with the remembered ids and the retract window), so it replays on its own.
        A file is never split before its inputs take as many bytes as the snapshots it
        starts with, so snapshots never take more than half of a split recording.
        The files share a set id and count up (the ``mcsm`` metadata's ``set`` and
        ``set_index``), which is how readers order a set and find gaps (:mod:`mcsm.recset`).

    Raises
    ------
    RecordingError
        If the file (or, with splitting, any file of the set) exists or the layout is
        unknown.
    OSError
        If the file cannot be created or written.
    """

    def __init__(self, path: str | os.PathLike[str], *, fsync: bool = False,
                 layout: str | None = None, split_bytes: int = 0,
                 split_s: float = 0.0) -> None:
        self.base = Path(path)
        self.layout = layout or os.environ.get(LAYOUT_ENV) or DEFAULT_LAYOUT
        if self.layout not in LAYOUTS:
            raise RecordingError(str(self.base), f"unknown recording layout {self.layout!r} "
                                 f"(expected one of {', '.join(LAYOUTS)})")
        self.split_bytes = max(0, int(split_bytes))
        self.split_s = max(0.0, float(split_s))
        self.splitting = bool(self.split_bytes or self.split_s)
        self.set_id = uuid.uuid4().hex if self.splitting else ""
        self.index = 0
        self.paths: list[Path] = []
        self._fsync = fsync
        self._states: dict[str, MapState] = {}
        self._configs: dict[str, dict[str, Any]] = {}
        first = split_name(self.base, 0) if self.splitting else self.base
        taken = ([p for p in self.base.parent.glob(f"{self.base.stem}_[0-9]*{self.base.suffix}")]
                 if self.splitting and self.base.parent.is_dir() else [])
        if first.exists() or taken:
            raise RecordingError(str(first if first.exists() else taken[0]),
                                 "exists; refusing to overwrite a recording")
        self.n_inputs = 0
        self.closed = False
        self._open(first)

    def _open(self, path: Path) -> None:
        """Start the file ``path``: header, schemas, channels, the ``mcsm`` metadata."""
        if path.exists():
            raise RecordingError(str(path), "exists; refusing to overwrite a recording")
        path.parent.mkdir(parents=True, exist_ok=True)
        self.path = path
        self._fh: BinaryIO = open(path, "xb")  # noqa: SIM115 - closed in close()
        self._file_open = True
        self.paths.append(path)
        self._snap_seq: dict[str, int] = {}  # map -> seq of its last snapshot in this file
        self._has_inputs: set[str] = set()  # maps with an input in this file
        self._opened = time.monotonic()
        self._w = _new_writer(self._fh, self.layout, f"mcsm {__version__}", path.parent)
        self._channels: dict[str, int] = {}
        schema_ids: dict[str, int] = {}
        for topic, (name, filename) in _SCHEMAS.items():
            if name not in schema_ids or self.layout == "flat":
                schema_ids[name] = self._w.register_schema(name, "jsonschema",
                                                           schema_bytes(filename))
            self._channels[topic] = self._w.register_channel(topic, "msgpack", schema_ids[name])
        fmt = 1 if self.layout == "flat" else FORMAT_VERSION
        meta = {"software": f"mcsm {__version__}", "format": f"mcsm recording v{fmt}",
                "arithmetic_version": str(ARITHMETIC_VERSION)}
        if self.splitting:
            meta.update({"set": self.set_id, "set_index": str(self.index)})
        self._w.add_metadata("mcsm", meta)
        self._w.flush()
        self._start_size = self._size()  # grows by the snapshots a split file starts with

    def _add(self, topic: str, obj: dict[str, Any], publish_ns: int, seq: int) -> None:
        data = wire.pack({"v": wire.VERSION, **obj})
        # log_time: when the record is written; publish_time: when it came about (receive
        # time of an input), so publish_time <= log_time as MCAP readers expect
        log_ns = max(time.time_ns(), int(publish_ns))
        self._w.add_message(self._channels[topic], log_time=log_ns, data=data,
                            publish_time=int(publish_ns), sequence=int(seq) & 0xFFFFFFFF)

    def _flush(self, sync: bool) -> None:
        self._w.flush()
        if sync:
            os.fsync(self._fh.fileno())

    def config(self, state: MapState, checkpoint_every: int, server_id: str = "",
               restored_from: str | None = None) -> None:
        """Record the options that rebuild ``state``'s empty map (once per map, first). The
        recorder keeps ``state`` to snapshot it at the start of the next file of a split
        recording."""
        now = time.time_ns()
        rec = {"map": state.name, "options": state.map.options(),
               "checkpoint_every": int(checkpoint_every), "time_ns": now,
               "snapshot_every": state.history.snapshot_every,
               "snapshots_kept": state.history.snapshots_kept,
               "retract_window_bytes": state.history.max_bytes,
               "gate_defer": (None if state.deferral is None
                              else state.deferral.options.to_dict()),
               "server_id": server_id, "restored_from": restored_from,
               "software": f"mcsm {__version__}",
               "arithmetic_version": ARITHMETIC_VERSION}
        self._states[state.name] = state
        self._configs[state.name] = rec
        self._add(TOPIC_CONFIG, rec, now, 0)
        self._flush(self._fsync)

    def input(self, op: str, map_name: str, seq: int, recv_ns: int, sender: str,
              request_id: str, payload: bytes) -> None:
        """Record one applied input and flush it (call before acknowledging). With
        splitting, a full file is closed after the input and the next one started."""
        self._add(INPUT_TOPICS[op], {"map": map_name, "seq": seq, "recv_ns": recv_ns,
                                     "sender": sender, "id": request_id,
                                     "request": bytes(payload)}, recv_ns, seq)
        self._flush(self._fsync)
        self.n_inputs += 1
        self._has_inputs.add(map_name)
        if self._split_due():
            self.split()

    def checkpoint(self, map_name: str, seq: int, digest: str, reason: str) -> None:
        self._add(TOPIC_CHECKPOINT, {"map": map_name, "seq": seq, "digest": digest,
                                     "reason": reason}, time.time_ns(), seq)
        self._flush(self._fsync)

    def snapshot(self, state: MapState, reason: str = "periodic") -> None:
        """Record ``state``'s whole map (versioned, with its digest and seq), the request ids
        it remembers and, when the file starts from this snapshot (a split file's first
        record, a restored server's first), its retract window if that reaches back before it
        (:mod:`mcsm.carry`); flush it. ``--restore`` starts from
        the latest one plus the inputs after it. A second snapshot of the same seq in one
        file is skipped (a split's first snapshot and a periodic one can coincide)."""
        first = state.name not in self._snap_seq and state.name not in self._has_inputs
        if self._snap_seq.get(state.name) == state.seq:
            return
        now = time.time_ns()
        rec: dict[str, Any] = {
            "map": state.name, "seq": state.seq, "digest": state.digest(),
            "format": SNAPSHOT_FORMAT, "reason": reason, "verdicts": dict(state.verdicts),
            "deferral": (None if state.deferral is None else state.deferral.state.encode()),
            "ids": encode_ids(state.id_columns()),
            "state": encode_snapshot(state.map.snapshot())}
        if first and state.history.window_start < state.seq:
            window = encode_window(state.history)
            if window is not None:
                rec["window"] = window
            else:
                log.warning("map %r: its retract window holds inputs applied without their "
                            "bytes; %s replayed alone starts its window at seq %d",
                            state.name, self.path, state.seq)
        self._add(TOPIC_SNAPSHOT, rec, now, state.seq)
        self._snap_seq[state.name] = state.seq
        self._flush(self._fsync)
        del rec
        _trim_heap()

    def _split_due(self) -> bool:
        if not self.splitting:
            return False
        size = self._size()
        if size - self._start_size < self._start_size:  # fewer input bytes than snapshots
            return False
        if self.split_bytes and size >= self.split_bytes:
            return True
        return bool(self.split_s) and time.monotonic() - self._opened >= self.split_s

    def _size(self) -> int:
        pos = getattr(self._w, "_pos", None)
        return int(pos) if pos is not None else int(self._fh.tell())

    def split(self) -> None:
        """Close this file (a ``split`` checkpoint per map, the summary) and start the next:
        every map's config and a snapshot (``reason: split``)."""
        for name, st in self._states.items():
            self.checkpoint(name, st.seq, st.digest(), "split")
        self._close_file()
        self.index += 1
        self._file_open = False
        self._open(split_name(self.base, self.index))
        for rec in self._configs.values():
            self._add(TOPIC_CONFIG, {**rec, "time_ns": time.time_ns()}, time.time_ns(), 0)
        for st in self._states.values():
            self.snapshot(st, reason="split")
        self._start_size = self._size()
        log.info("recording continues in %s (file %d of set %s)", self.path, self.index,
                 self.set_id)

    def _close_file(self) -> None:
        """Summary, footer, fsync, close. A failure leaves the file cut (no summary) and is
        raised after the file was closed."""
        try:
            if getattr(self._w, "failed", False):
                raise OSError(f"{self.path}: an earlier write failed; the file ends after "
                              "its last complete record")
            self._w.finish()
            self._fh.flush()
            os.fsync(self._fh.fileno())
        finally:
            close_spill = getattr(self._w, "close_spill", None)
            if close_spill is not None:
                close_spill()
            try:
                self._fh.close()
            except OSError as exc:
                log.error("closing %s: %s", self.path, exc)

    def close(self) -> None:
        """Write the summary and footer and close the file (idempotent).

        Raises
        ------
        OSError
            If that fails (full disk): the file is closed anyway and left cut, with every
            complete record before (``mcsm recover`` indexes it).
        """
        if self.closed:
            return
        self.closed = True
        if self._file_open:
            self._file_open = False
            self._close_file()


# --------------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------------

@dataclass
class RecordItem:
    topic: str
    data: dict[str, Any]
    log_time_ns: int


def _ends_with_footer(path: Path, size: int) -> bool:
    if size < 2 * len(_MAGIC) + 29:
        return False
    with open(path, "rb") as fh:
        fh.seek(size - len(_MAGIC))
        return fh.read(len(_MAGIC)) == _MAGIC


def _summary_crc_ok(path: Path, size: int, footer: Footer) -> bool:
    """Check the footer's summary CRC (MCAP spec: summary start .. summary_offset_start)."""
    footer_start = size - len(_MAGIC) - 29
    start = footer.summary_start or footer_start
    if not 0 < start <= footer_start:
        return False
    crc = 0
    with open(path, "rb") as fh:
        fh.seek(start)
        remaining = size - len(_MAGIC) - 4 - start
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

    Raises
    ------
    RecordingError
        If the file is not an MCAP file (no magic and header).
    OSError
        If the file cannot be opened.
    """

    def __init__(self, path: str | os.PathLike[str],
                 progress: Callable[[int, int], None] | None = None) -> None:
        self.path = Path(path)
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
        """The ``mcsm`` metadata's arithmetic version (1 for files that do not say)."""
        try:
            return int(self.metadata.get("mcsm", {}).get("arithmetic_version",
                                                          LEGACY_ARITHMETIC_VERSION))
        except ValueError:
            return LEGACY_ARITHMETIC_VERSION

    def _stopped(self, exc: BaseException, at: int, what: str = "") -> None:
        self.stop_offset = at
        eof = isinstance(exc, (EndOfFile, EOFError, struct.error))
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
        for rec in self.raw():
            if not isinstance(rec, Message):
                continue
            topic = self.channels[rec.channel_id].topic
            try:
                data = wire.unpack(rec.data, max_bytes=MAX_RECORD_BYTES)
            except McsmError as exc:
                self.tail_error = self.damage = f"undecodable record on {topic}: {exc}"
                return
            yield RecordItem(topic, data, int(rec.log_time))


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


# --------------------------------------------------------------------------------------------
# Replay
# --------------------------------------------------------------------------------------------

@dataclass
class Checkpoint:
    map: str
    seq: int
    digest: str
    reason: str


@dataclass
class ReplayReport:
    """What :func:`replay` found."""

    path: str
    states: dict[str, MapState] = field(default_factory=dict)
    configs: dict[str, dict[str, Any]] = field(default_factory=dict)
    n_inputs: int = 0
    ops: Counter[str] = field(default_factory=Counter)
    checkpoints: list[Checkpoint] = field(default_factory=list)
    checkpoints_ok: int = 0
    snapshots_loaded: int = 0
    n_skipped: int = 0  # inputs before a snapshot replay started from (ids remembered only)
    #: checkpoints of maps recorded by another arithmetic version: not comparable, not checked
    checkpoints_other_arithmetic: int = 0
    divergence: str | None = None
    complete: bool = False
    cut: bool = False
    damage: str | None = None
    tail_error: str | None = None
    first_time_ns: int | None = None
    last_time_ns: int | None = None
    elapsed_s: float = 0.0
    library: str = ""
    #: arithmetic version each map was recorded with (1 when the recording does not say)
    arithmetic_versions: dict[str, int] = field(default_factory=dict)
    #: the files read, in order (a split recording read from a snapshot skips the first ones)
    files: list[str] = field(default_factory=list)

    @property
    def identical(self) -> bool:
        """No divergence among what was compared (see also ``complete``, ``other_arithmetic``)."""
        return self.divergence is None

    @property
    def other_arithmetic(self) -> dict[str, int]:
        """Maps recorded by an arithmetic version other than this core's, with that version."""
        return {n: v for n, v in self.arithmetic_versions.items() if v != ARITHMETIC_VERSION}

    def final_digests(self) -> dict[str, str]:
        return {name: st.map.state_digest() for name, st in self.states.items()}


PathArg = str | os.PathLike[str]


def _path_list(path: PathArg | Sequence[PathArg]) -> list[Path]:
    if isinstance(path, (str, os.PathLike)):
        return [Path(path)]
    paths = [Path(p) for p in path]
    if not paths:
        raise RecordingError("", "no recording given")
    return paths


class _Chain:
    """The records of several files of a split recording, in order, as one stream.

    A file other than the last must be complete: reading stops at the first one that is not
    (``tail_error`` and ``damage`` then name it). Afterwards ``complete``, ``cut``,
    ``damage`` and ``tail_error`` describe the set as :class:`RecordingReader` describes one
    file."""

    def __init__(self, paths: list[Path],
                 progress: Callable[[int, int], None] | None = None) -> None:
        self.paths = paths
        self.total = sum(p.stat().st_size for p in paths)
        self.progress = progress
        self.reader: RecordingReader | None = None
        self.complete = False
        self.damage: str | None = None
        self.tail_error: str | None = None
        self.library = ""

    @property
    def cut(self) -> bool:
        return not self.complete and self.damage is None and self.tail_error is not None

    @property
    def arithmetic_version(self) -> int:
        return self.reader.arithmetic_version if self.reader is not None \
            else LEGACY_ARITHMETIC_VERSION

    def __iter__(self) -> Iterator[RecordItem]:
        done = 0
        for k, path in enumerate(self.paths):
            def report(n: int, _total: int, base: int = done) -> None:
                if self.progress is not None:
                    self.progress(base + n, self.total)

            reader = RecordingReader(path, report if self.progress is not None else None)
            self.reader = reader
            yield from reader
            if k == 0:
                self.library = reader.library
            done += reader.size
            last = k == len(self.paths) - 1
            self.complete, self.damage = reader.complete, reader.damage
            self.tail_error = reader.tail_error
            if not reader.complete:
                if not last:
                    where = f"{path.name} (file {k + 1} of {len(self.paths)})"
                    self.tail_error = f"{where}: {reader.tail_error}"
                    self.damage = None if reader.damage is None else f"{where}: {reader.damage}"
                return


@dataclass
class _Start:
    """Where ``--restore`` starts one map: a snapshot's seq and what its retract window
    (carried or not) covers."""

    seq: int
    window_ids: frozenset[str]


def _start_points(paths: list[Path]) -> tuple[int, dict[str, int]]:
    """For a replay from snapshots: the first file to read and, per map, the snapshot to
    start from: the latest one such that every later retract or reinstate targets an update
    after it or in the window it carries (a target before it could not be found). Files are
    read from the last one back, only as far as needed."""
    snaps: dict[str, list[_Start]] = {}  # map -> candidates, latest first
    retracts: dict[str, list[tuple[int, str]]] = {}  # map -> (seq, target)
    update_seq: dict[tuple[str, str], int] = {}  # (map, update id) -> seq
    maps: set[str] = set()
    chosen: dict[str, int] = {}
    for k in range(len(paths) - 1, -1, -1):
        here: dict[str, list[_Start]] = {}
        for item in RecordingReader(paths[k]):
            d = item.data
            name = d.get("map")
            if not isinstance(name, str):
                continue
            if item.topic == TOPIC_CONFIG:
                maps.add(name)
            elif item.topic == TOPIC_SNAPSHOT:
                w = d.get("window")
                ids = frozenset(str(e.get("id")) for e in w.get("log", [])
                                if isinstance(e, dict)) if isinstance(w, dict) else frozenset()
                here.setdefault(name, []).append(_Start(int(d.get("seq", 0)), ids))
            elif item.topic in (INPUT_TOPICS["update"],):
                update_seq[(name, str(d.get("id")))] = int(d.get("seq", 0))
            elif TOPIC_OPS.get(item.topic) in ("retract", "reinstate"):
                try:
                    target = wire.unpack(bytes(d["request"])).get("target")
                except (McsmError, KeyError, TypeError):
                    continue
                retracts.setdefault(name, []).append((int(d.get("seq", 0)), str(target)))
        for name, cands in here.items():
            snaps.setdefault(name, [])[0:0] = cands
        chosen = {}
        for name in maps:
            for cand in reversed(snaps.get(name, [])):
                if all(update_seq.get((name, t), -1) > cand.seq or t in cand.window_ids
                       for r, t in retracts.get(name, []) if r > cand.seq):
                    chosen[name] = cand.seq
                    break
        if maps and set(chosen) == maps:
            return k, chosen
    return 0, chosen


def replay(path: PathArg | Sequence[PathArg], *, sink: Recorder | None = None,
           progress: Callable[[int, int], None] | None = None,
           lru_size: int = DEFAULT_LRU, id_ttl_s: float = DEFAULT_ID_TTL_S,
           server_id: str = "", stop_after: int | None = None,
           from_snapshot: bool = False, device: object = "cpu") -> ReplayReport:
    """Rebuild every map of a recording (one file, or the files of a split recording in set
    order: :func:`mcsm.recset.resolve`) and check its digests at every checkpoint and
    snapshot. ``device``: where the rebuilt maps keep their edges (``StochasticMap``'s
    argument; the digests are the same on every device).

    With ``from_snapshot`` (``mcsm serve --restore``), each map starts from its latest
    snapshot (verified by its digest; with the request ids and, if it carries one, the
    retract window it records) and only the inputs after it are applied; an earlier snapshot
    is taken when a later retract targets an update before the latest. Files before the one
    holding that snapshot are not read. A sink then receives that snapshot and the tail, so
    the new file replays on its own.

    A map recorded by another arithmetic version (:data:`mcsm.core.ARITHMETIC_VERSION`) is
    rebuilt with this core's arithmetic, and its checkpoints are not compared (they cannot
    match bit for bit); ``other_arithmetic`` names such maps. With a ``sink``, that sink's new
    checkpoints carry the digests of this arithmetic, so the new file replays on its own.

    Parameters
    ----------
    path : the recording, or the files of a split recording in order (complete, cut or
        damaged: replay stops at the first cut or damage)
    sink : if given, every config, input and checkpoint is written again into this recorder
        (used by ``mcsm serve --restore``: the new file replays on its own)
    progress : called with (bytes read, bytes of all files) at most ten times a second
    lru_size, id_ttl_s : how many request ids each map remembers, and how long
    stop_after : stop after this many inputs (all maps together), e.g. to inspect a past state

    Returns
    -------
    ReplayReport
        ``divergence`` names the first mismatch (replay stops there) or is None.

    Raises
    ------
    RecordingError
        If the file is not a readable mcsm recording.
    """
    t0 = time.perf_counter()
    paths = _path_list(path)
    rep = ReplayReport(path=str(paths[0]) if len(paths) == 1
                       else f"{paths[0]} .. {paths[-1].name} ({len(paths)} files)")
    start: dict[str, int] = {}  # map -> seq of the snapshot to start from
    first = 0
    if from_snapshot:
        first, start = _start_points(paths)
    rep.files = [str(p) for p in paths[first:]]
    reader = _Chain(paths[first:], progress)
    for item in reader:
        if stop_after is not None and rep.n_inputs >= stop_after:
            break
        d = item.data
        if rep.first_time_ns is None:
            rep.first_time_ns = item.log_time_ns
        rep.last_time_ns = item.log_time_ns
        name = d.get("map")
        src = reader.reader.path if reader.reader is not None else paths[0]
        if not isinstance(name, str):
            raise RecordingError(str(src), f"record on {item.topic} without a map name")
        if item.topic == TOPIC_CONFIG:
            if name in rep.states:
                continue  # a map's config is written once per file; ignore repeats
            try:
                smap = StochasticMap.from_options(dict(d["options"]), device=device)
                defer = DeferOptions.from_dict(d.get("gate_defer"))  # absent: no deferral
                window = d.get("retract_window_bytes")  # absent: unbounded (older files)
            except (McsmError, KeyError, TypeError, ValueError) as exc:
                raise RecordingError(str(src), f"bad options for map {name!r}: {exc}"
                                     ) from None
            st = MapState(name, smap, lru_size, id_ttl_s,
                          snapshot_every=int(d.get("snapshot_every", DEFAULT_SNAPSHOT_EVERY)),
                          snapshots_kept=int(d.get("snapshots_kept", DEFAULT_SNAPSHOTS_KEPT)),
                          gate_defer=defer,
                          retract_window_bytes=None if window is None else int(window))
            rep.states[name] = st
            rep.configs[name] = dict(d)
            version = d.get("arithmetic_version", reader.arithmetic_version)
            rep.arithmetic_versions[name] = version if type(version) is int else -1
            if version != ARITHMETIC_VERSION:
                log.warning("%s: map %r was recorded by arithmetic version %s; this mcsm "
                            "computes with version %d: its checkpoints are not compared",
                            src, name, version, ARITHMETIC_VERSION)
            if sink is not None:
                sink.config(st, int(d.get("checkpoint_every", 100)), server_id=server_id,
                            restored_from=str(rep.path))
            continue
        st_or_none = rep.states.get(name)
        if st_or_none is None:
            raise RecordingError(str(src), f"record for map {name!r} before its config")
        st = st_or_none
        if item.topic == TOPIC_SNAPSHOT:
            seq = int(d["seq"])
            s0 = start.get(name)
            if s0 is not None and seq < s0:
                continue  # an earlier snapshot than the one this replay starts from
            if seq == s0 or st.seq == 0 < seq:
                # start here: the inputs before were skipped (or are not in these files)
                try:
                    _load_snapshot(st, d, device)
                except (McsmError, KeyError, TypeError, ValueError) as exc:
                    raise RecordingError(str(src), f"unreadable snapshot of map {name!r} "
                                         f"at seq {seq}: {exc}") from None
                rep.snapshots_loaded += 1
            elif seq != st.seq:
                rep.divergence = (f"map {name!r}: snapshot at seq {seq} but replay is at "
                                  f"seq {st.seq}")
                break
            if name not in rep.other_arithmetic:
                got = st.digest()
                if got != str(d["digest"]):
                    rep.divergence = (f"map {name!r}: snapshot digest differs at seq {seq} "
                                      f"(recorded {str(d['digest'])[:16]}..., replayed "
                                      f"{got[:16]}...)")
                    break
                rep.checkpoints_ok += 1
            rep.checkpoints.append(Checkpoint(name, seq, str(d["digest"]), "snapshot"))
            if sink is not None:
                sink.snapshot(st, reason=str(d.get("reason", "periodic")))
            continue
        if item.topic == TOPIC_CHECKPOINT and name in start and st.seq < start[name]:
            continue  # before the snapshot this replay starts from is loaded
        if item.topic == TOPIC_CHECKPOINT:
            cp = Checkpoint(name, int(d["seq"]), str(d["digest"]), str(d.get("reason", "")))
            rep.checkpoints.append(cp)
            if cp.seq != st.seq:
                rep.divergence = (f"map {name!r}: checkpoint at seq {cp.seq} but replay is at "
                                  f"seq {st.seq}")
                break
            if name in rep.other_arithmetic:
                rep.checkpoints_other_arithmetic += 1
                if sink is not None:
                    sink.checkpoint(name, cp.seq, st.digest(), cp.reason)
                continue
            got = st.digest()
            if got != cp.digest:
                rep.divergence = (f"map {name!r}: digest differs at seq {cp.seq} "
                                  f"(recorded {cp.digest[:16]}..., replayed {got[:16]}...)")
                break
            rep.checkpoints_ok += 1
            if sink is not None and cp.reason != "split":  # the sink splits on its own
                sink.checkpoint(name, cp.seq, cp.digest, cp.reason)
            continue
        op = TOPIC_OPS.get(item.topic)
        if op is None:
            log.warning("%s: ignoring records on unknown topic %s", src, item.topic)
            continue
        seq = int(d["seq"])
        if seq <= start.get(name, -1):  # before the snapshot: remember the id, skip the work
            try:
                req = decode_input(op, bytes(d["request"]), st.n_samples)
            except McsmError as exc:
                rep.divergence = f"map {name!r}: input seq {seq} ({op}) does not decode: {exc}"
                break
            st.remember(op, req, seq, int(d["recv_ns"]))
            rep.n_skipped += 1
            continue
        if seq != st.seq + 1:
            rep.divergence = (f"map {name!r}: input seq {seq} follows seq {st.seq} "
                              "(gap or reordering)")
            break
        try:
            payload = bytes(d["request"])
            req = decode_input(op, payload, st.n_samples)
            ack = st.apply(op, req, time_ns=int(d["recv_ns"]), payload=payload)
        except McsmError as exc:
            rep.divergence = (f"map {name!r}: input seq {seq} ({op}) was refused on replay: "
                              f"{type(exc).__name__}: {exc}")
            break
        rep.n_inputs += 1
        rep.ops[op] += 1
        if sink is not None:
            sink.input(op, name, ack.seq, int(d["recv_ns"]), str(d.get("sender", "")),
                       str(d.get("id", "")), payload)
    rep.complete = reader.complete
    stopped_early = rep.divergence is not None or stop_after is not None
    rep.cut = reader.cut and not stopped_early
    rep.damage = None if stopped_early else reader.damage
    rep.tail_error = reader.tail_error
    rep.library = reader.library
    rep.elapsed_s = time.perf_counter() - t0
    return rep


def _load_snapshot(st: MapState, d: dict[str, Any], device: object = "cpu") -> None:
    """Continue ``st`` from the snapshot record ``d``: its map (its edges on ``device``),
    deferral state, remembered ids (when recorded) and retract window (when carried).

    Raises
    ------
    McsmError, KeyError, TypeError, ValueError
        If the record does not decode.
    """
    snap = decode_snapshot(d["state"], st.n_samples)
    dfr = d.get("deferral")
    ids = d.get("ids")
    st.restore(int(d["seq"]), StochasticMap.from_snapshot(snap, device=device),
               d.get("verdicts", {}),
               None if dfr is None else DeferState.decode(dfr, st.n_samples),
               None if ids is None else decode_ids(ids))
    window = d.get("window")
    if window is not None:
        decode_window(window, st.history, st.n_samples)


# --------------------------------------------------------------------------------------------
# Recovery
# --------------------------------------------------------------------------------------------

@dataclass
class RecoverReport:
    """What :func:`recover` copied."""

    source_complete: bool
    source_cut: bool
    damage: str | None
    tail_error: str | None
    messages: Counter[str] = field(default_factory=Counter)  # per topic
    chunks_after_damage: int = 0
    bytes_written: int = 0

    @property
    def n_inputs(self) -> int:
        return sum(n for t, n in self.messages.items() if t in TOPIC_OPS)


def recover(src: str | os.PathLike[str], dst: str | os.PathLike[str],
            progress: Callable[[int, int], None] | None = None) -> RecoverReport:
    """Write a clean, indexed copy of every complete record of ``src`` (cut or damaged) to the
    new file ``dst``.

    Records are copied as they are, except that each message gets ``publish_time <=
    log_time`` (files of format 1 had them the other way round). After damage in a chunked
    file, the intact chunks that follow (CRC checked) are copied too.

    Raises
    ------
    RecordingError
        If ``src`` is not an MCAP file or ``dst`` exists.
    OSError
        If a file cannot be opened.
    """
    reader = RecordingReader(src, progress)
    out = Path(dst)
    if out.exists():
        raise RecordingError(str(out), "exists; refusing to overwrite")
    with open(out, "xb") as fo:
        w = ChunkPerInputWriter(fo, lz4=True, library=f"mcsm {__version__} recover")
        schema_ids: dict[tuple[str, str, bytes], int] = {}
        channel_ids: dict[tuple[str, str, int], int] = {}
        channels: dict[int, Channel] = {}
        schemas: dict[int, Schema] = {}
        counts: Counter[str] = Counter()

        def copy(r: Any) -> None:
            if isinstance(r, Schema):
                schemas[r.id] = r
            elif isinstance(r, Channel):
                channels[r.id] = r
            elif isinstance(r, Metadata):
                w.add_metadata(r.name, dict(r.metadata))
            elif isinstance(r, Message) and r.channel_id in channels:
                ch = channels[r.channel_id]
                sid = 0
                sch = schemas.get(ch.schema_id)
                if sch is not None:
                    skey = (sch.name, sch.encoding, bytes(sch.data))
                    if skey not in schema_ids:
                        schema_ids[skey] = w.register_schema(sch.name, sch.encoding, sch.data)
                    sid = schema_ids[skey]
                ckey = (ch.topic, ch.message_encoding, sid)
                if ckey not in channel_ids:
                    channel_ids[ckey] = w.register_channel(ch.topic, ch.message_encoding, sid,
                                                           dict(ch.metadata))
                lo, hi = sorted((int(r.log_time), int(r.publish_time)))
                w.add_message(channel_ids[ckey], log_time=hi, data=r.data, publish_time=lo,
                              sequence=r.sequence)
                counts[ch.topic] += 1

        for r in reader.raw():
            copy(r)
        n_after = 0
        if reader.damage is not None:
            for _, records in scan_chunks(src, reader.stop_offset + 1):
                n_after += 1
                for r in records:
                    copy(r)
        w.finish()
        fo.flush()
        os.fsync(fo.fileno())
    return RecoverReport(source_complete=reader.complete, source_cut=reader.cut,
                         damage=reader.damage, tail_error=reader.tail_error, messages=counts,
                         chunks_after_damage=n_after, bytes_written=out.stat().st_size)


# --------------------------------------------------------------------------------------------
# Progress
# --------------------------------------------------------------------------------------------

class Progress:
    """Progress over bytes: a tqdm bar when ``stream`` is a terminal; otherwise a plain line
    (``label: 40% (12.0 of 30.0 MB)``) every ``every_s`` seconds and a last one at the end
    (none for a run shorter than ``every_s``), so that logs get what a bar would say and
    never a ``\\r``."""

    def __init__(self, label: str, stream: Any = None, every_s: float = 10.0) -> None:
        self.label = label
        self.out = stream if stream is not None else sys.stderr
        self.every_s = every_s
        self._bar: Any = None
        self._tty = bool(getattr(self.out, "isatty", lambda: False)())
        self._last = time.monotonic()
        self._lines = 0
        self.done = False

    def __call__(self, done: int, total: int) -> None:
        if self.done:
            return
        if self._tty:
            if self._bar is None:
                from tqdm import tqdm

                self._bar = tqdm(total=total, desc=self.label, unit="B", unit_scale=True,
                                 file=self.out, leave=True, dynamic_ncols=True)
            self._bar.update(done - self._bar.n)
        else:
            now = time.monotonic()
            if now - self._last >= self.every_s or (done >= total and self._lines):
                self._last = now
                self._lines += 1
                frac = 1.0 if total <= 0 else min(1.0, done / total)
                self.out.write(f"{self.label}: {100 * frac:.0f}% ({done / 1e6:.1f} of "
                               f"{total / 1e6:.1f} MB)\n")
                self.out.flush()
        if done >= total:
            self.close()

    def close(self) -> None:
        if self._bar is not None and not self.done:
            self._bar.close()
        self.done = True


def progress_bar(stream: Any = None, label: str = "replaying the recording") -> Progress:
    """A :class:`Progress` over bytes read (a bar on a terminal, plain lines otherwise)."""
    return Progress(label, stream)
