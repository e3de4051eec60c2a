"""Whether an MCAP file is an mcsm recording at all, before a command reads it as one.

``mcsm export foxglove`` writes MCAP files too (Foxglove's protobuf scene); ``mcsm replay``,
``inspect``, ``recover``, ``cat``, ``plot`` and ``export`` given such a file must say "not an
mcsm recording" (exit 2), not call it damaged or write an empty copy. An mcsm recording's
first message is on one of its own topics (``/mcsm/config``, the inputs, checkpoints,
snapshots) in ``msgpack``; schema, channel and metadata records come before it.
"""

from __future__ import annotations

import os
from itertools import islice

from mcsm.ops import INPUT_TOPICS

#: topics of an mcsm recording (mcsm.recording's)
RECORDING_TOPICS = frozenset(["/mcsm/config", "/mcsm/checkpoint", "/mcsm/snapshot",
                              *INPUT_TOPICS.values()])
#: records read at most before the verdict (a recording's first message comes much sooner)
MAX_RECORDS = 10_000


def not_a_recording(path: str | os.PathLike[str]) -> str | None:
    """Why the MCAP file ``path`` is not an mcsm recording, or None when it is one (or when it
    cannot tell: unreadable, not MCAP, no message at all; the reader says what is wrong).

    Reads records up to the first message only: cheap on any file size.
    """
    from mcap.exceptions import McapError
    from mcap.records import Channel, Message, Schema
    from mcap.stream_reader import StreamReader

    channels: dict[int, Channel] = {}
    schemas: dict[int, str] = {}
    try:
        with open(path, "rb") as fh:
            for rec in islice(StreamReader(fh, skip_magic=False).records, MAX_RECORDS):
                if isinstance(rec, Schema):
                    schemas[rec.id] = rec.name
                elif isinstance(rec, Channel):
                    channels[rec.id] = rec
                elif isinstance(rec, Message):
                    ch = channels.get(rec.channel_id)
                    if ch is None:
                        return None
                    if ch.topic in RECORDING_TOPICS and ch.message_encoding == "msgpack":
                        return None
                    schema = schemas.get(ch.schema_id, "")
                    return (f"not an mcsm recording (its first message is on {ch.topic}, "
                            f"{ch.message_encoding}{' ' + schema if schema else ''}: a file "
                            "for viewers, like those `mcsm export foxglove` writes)")
    except (McapError, OSError, ValueError, EOFError):
        return None
    return None
