"""Recovery: :func:`recover` writes a clean, indexed copy of every complete record of a cut or
damaged recording (``mcsm recover``); :class:`RecoverReport` says what it copied."""

from __future__ import annotations

import os
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcap.records import (
    Channel,
    Message,
    Metadata,
    Schema,
)

from mcsm import __version__
from mcsm.log.chunkwriter import ChunkPerInputWriter
from mcsm.log.reader import RecordingReader, scan_chunks
from mcsm.log.topics import TOPIC_OPS, RecordingError


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
    out = Path(dst)
    if out.exists():
        raise RecordingError(str(out), "exists; refusing to overwrite")
    reader = RecordingReader(src, progress)
    created = False  # the output is removed again only if this call made it
    try:
        with open(out, "xb") as fo:
            created = True
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
    except BaseException:
        if created:
            out.unlink(missing_ok=True)
        raise
    return RecoverReport(source_complete=reader.complete, source_cut=reader.cut,
                         damage=reader.damage, tail_error=reader.tail_error, messages=counts,
                         chunks_after_damage=n_after, bytes_written=out.stat().st_size)
