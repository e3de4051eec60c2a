"""The recorder: :class:`Recorder` writes a map's config, every accepted input, checkpoints and
snapshots to a recording (one file, or a split set: :func:`split_name`), each flushed to the OS
before the call returns."""

from __future__ import annotations

import logging
import os
import time
import uuid
from pathlib import Path
from typing import Any, BinaryIO

from mcsm import __version__, wire
from mcsm.core import ARITHMETIC_VERSION
from mcsm.log import snapchunks
from mcsm.log.chunkwriter import new_writer, trim_heap
from mcsm.log.topics import (
    DEFAULT_LAYOUT,
    FORMAT_VERSION,
    INPUT_TOPICS,
    LAYOUT_ENV,
    LAYOUTS,
    SCHEMAS,
    SNAPSHOT_FORMAT,
    TOPIC_CHECKPOINT,
    TOPIC_CONFIG,
    RecordingError,
    schema_bytes,
)
from mcsm.map.carry import encode_ids, encode_window
from mcsm.map.state import MapState

log = logging.getLogger(__name__)

def split_name(base: str | os.PathLike[str], index: int) -> Path:
    """File ``index`` of a split recording whose ``--record`` path is ``base``:
    ``run.mcap`` gives ``run_0000.mcap``, ``run_0001.mcap``, ... (``mcsm serve --split-size``)."""
    b = Path(base)
    return b.with_name(f"{b.stem}_{int(index):04d}{b.suffix or '.mcap'}")



def new_recording_problem(path: Path) -> str | None:
    """Why a recording the user named (``--record PATH``) cannot be started, or None.

    A recording is never overwritten, and the folder must exist: the writer creates a
    missing one (the default ``recordings/``), but a mistyped path would record somewhere
    unexpected."""
    if path.exists():
        return "exists; a recording is never overwritten: name a new file"
    if not path.parent.is_dir():
        return f"its folder {path.parent} does not exist (create it first)"
    return None

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
        ``--split-duration``). The check follows each input, so every file but the last holds
        at least one input and ends at a clean close; the next file starts with every map's
        config and a snapshot (with the remembered ids and the retract window), so it replays
        on its own.
        A file is never split before its inputs take as many bytes as the snapshots it
        starts with, so snapshots never take more than half of a split recording.
        The files share a set id and count up (the ``mcsm`` metadata's ``set`` and
        ``set_index``), which is how readers order a set and find gaps (:mod:`mcsm.log.recset`).

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
        self._w = new_writer(self._fh, self.layout, f"mcsm {__version__}", path.parent)
        self._channels: dict[str, int] = {}
        schema_ids: dict[str, int] = {}
        for topic, (name, filename) in SCHEMAS.items():
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
            "state": state.map.snapshot()}
        if first and state.history.window_start < state.seq:
            window = encode_window(state.history)
            if window is not None:
                rec["window"] = window
            else:
                log.warning("map %r: its retract window holds inputs applied without their "
                            "bytes; %s replayed alone starts its window at seq %d",
                            state.name, self.path, state.seq)
        log_ns = time.time_ns()
        for topic, data in snapchunks.records(rec):  # one record, or a header and its parts
            self._w.add_message(self._channels[topic], log_time=log_ns, data=data,
                                publish_time=now, sequence=int(state.seq) & 0xFFFFFFFF)
        self._snap_seq[state.name] = state.seq
        self._flush(self._fsync)
        del rec
        trim_heap()

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
