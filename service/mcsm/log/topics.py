"""The recording's vocabulary: topics, schemas, layouts, format versions, its error type; the
format of a recording (MCAP recording of every accepted input, and deterministic replay).

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
``/mcsm/snapshot``          ``record_snapshot``: the whole state of a map after ``seq`` (or,
                            above 64 MiB, the header of a chunked one: :mod:`mcsm.log.snapchunks`)
``/mcsm/snapshot_part``     ``record_snapshot_part``: one part of a chunked snapshot
==========================  ===================================================================

The input topics are the table's (:data:`mcsm.map.ops.INPUT_TOPICS`). Each input carries the map's
sequence number (also the MCAP ``sequence``), the receive time (the MCAP ``publish_time``;
``log_time`` is when the record was written, never earlier), the sender and the request id.
Queries and exports change nothing and are not recorded; rejected inputs are not recorded. A
metadata record ``mcsm`` names the software and the core's arithmetic version
(:data:`mcsm.core.ARITHMETIC_VERSION`); recordings without it were made by arithmetic version
1.

Replay (:func:`mcsm.log.replay.replay`) reads the file with mcap's ``StreamReader`` only
(checking CRCs), because after a SIGKILL the file has no summary or footer; it decodes each
request with :mod:`mcsm.wire`, applies it through :class:`MapState` (the same code the live
server runs) and checks every checkpoint.

Every other module of :mod:`mcsm.log` imports its constants from here (this module imports
none of them).
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib import resources
from typing import Any

from mcsm.errors import McsmError
from mcsm.map import ops

TOPIC_CONFIG = "/mcsm/config"
TOPIC_CHECKPOINT = "/mcsm/checkpoint"
TOPIC_SNAPSHOT = "/mcsm/snapshot"
TOPIC_SNAPSHOT_PART = "/mcsm/snapshot_part"
"""One part of a chunked snapshot (:mod:`mcsm.log.snapchunks`)."""
INPUT_TOPICS = ops.INPUT_TOPICS
"""Recording topic of each state-changing operation (from the table, :mod:`mcsm.map.ops`)."""
TOPIC_OPS = ops.TOPIC_OPS
SCHEMAS = {TOPIC_CONFIG: ("mcsm.RecordConfig", "record_config.json"),
            TOPIC_CHECKPOINT: ("mcsm.RecordCheckpoint", "record_checkpoint.json"),
            TOPIC_SNAPSHOT: ("mcsm.RecordSnapshot", "record_snapshot.json"),
            TOPIC_SNAPSHOT_PART: ("mcsm.RecordSnapshotPart",
                                             "record_snapshot_part.json"),
            **{t: ("mcsm.RecordInput", "record_input.json") for t in INPUT_TOPICS.values()}}
MAX_RECORD_BYTES = (1 << 32) + (1 << 20)
"""Largest record read back: 4 GiB and a little, the most msgpack can hold, so that a
single-record snapshot written before snapshots were chunked (:mod:`mcsm.log.snapchunks`) reads
back; new files hold no record above the part size (64 MiB). A larger one stops the reader
loudly (:class:`RecordingError` from iteration): the records after it are never skipped."""
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
MCAP_MAGIC = b"\x89MCAP0\r\n"


class RecordingError(McsmError):
    """A recording cannot be read or written (not MCAP, unknown map, diverging replay)."""

    def __init__(self, path: str, reason: str) -> None:
        super().__init__(f"{path}: {reason}", path=path, reason=reason)


def schema_bytes(filename: str) -> bytes:
    """One JSON Schema of ``schemas/``, read through importlib.resources (works from a wheel)."""
    return resources.files("mcsm.schemas").joinpath(filename).read_bytes()


decode_input = ops.decode_input


# --------------------------------------------------------------------------------------------


@dataclass
class RecordItem:
    """One decoded record of a recording: its topic, its message, its MCAP log time."""

    topic: str
    data: dict[str, Any]
    log_time_ns: int
