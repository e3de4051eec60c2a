"""MCAP recording of every accepted input, and deterministic replay.

A recording is an MCAP file, unchunked (each record reaches the file at ``Writer.flush()``,
which the server calls before it acknowledges), with message encoding ``msgpack`` and one
channel per kind of record, each with a ``jsonschema`` schema record embedding the schema from
``schemas/``:

==========================  ===================================================================
topic                       message
==========================  ===================================================================
``/mcsm/config``            ``record_config``: a map's name and options (first, one per map)
``/mcsm/in/update``         ``record_input``: update or point update, exact request bytes
``/mcsm/in/remove``         ``record_input``: remove
``/mcsm/in/submap_import``  ``record_input``: submap import
``/mcsm/checkpoint``        ``record_checkpoint``: state digest after operation ``seq``
==========================  ===================================================================

Each input carries the map's sequence number (also the MCAP ``sequence``), the receive time
(the MCAP ``log_time``), the sender and the request id. Queries and exports change nothing
and are not recorded; rejected inputs are not recorded.

Replay (:func:`replay`) reads the file with mcap's ``StreamReader`` only, because after a
SIGKILL the file has no summary or footer and the seeking reader returns nothing
(``shared/notes/ecosystem.md`` §3.3); it decodes each request with :mod:`mcsm.wire`, applies it
through :class:`MapState` (the same code the live server runs) and checks every checkpoint.
"""

from __future__ import annotations

import logging
import os
import struct
import sys
import time
from collections import Counter, OrderedDict
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from importlib import resources
from pathlib import Path
from typing import Any, BinaryIO

from mcap.exceptions import McapError
from mcap.records import Channel, DataEnd, Footer, Message, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import Writer

from mcsm import __version__, wire
from mcsm.core.smap import StochasticMap
from mcsm.errors import InvalidOperation, McsmError, RequestIdReused
from mcsm.history import DEFAULT_SNAPSHOT_EVERY, DEFAULT_SNAPSHOTS_KEPT, History

log = logging.getLogger(__name__)

TOPIC_CONFIG = "/mcsm/config"
TOPIC_CHECKPOINT = "/mcsm/checkpoint"
INPUT_TOPICS = {"update": "/mcsm/in/update", "remove": "/mcsm/in/remove",
                "import": "/mcsm/in/submap_import", "retract": "/mcsm/in/retract",
                "reinstate": "/mcsm/in/reinstate"}
TOPIC_OPS = {v: k for k, v in INPUT_TOPICS.items()}
_SCHEMAS = {TOPIC_CONFIG: ("mcsm.RecordConfig", "record_config.json"),
            TOPIC_CHECKPOINT: ("mcsm.RecordCheckpoint", "record_checkpoint.json"),
            **{t: ("mcsm.RecordInput", "record_input.json") for t in INPUT_TOPICS.values()}}
MAX_RECORD_BYTES = 2 * wire.MAX_PAYLOAD_BYTES
DEFAULT_LRU = 100_000
"""Request ids (with their acks) each map remembers at most (about 60 MB at most)."""
DEFAULT_ID_TTL_S = 600.0
"""Seconds a request id is remembered (ten minutes: a server restart takes 1-8 s)."""


class RecordingError(McsmError):
    """A recording cannot be read or written (not MCAP, unknown map, diverging replay)."""

    def __init__(self, path: str, reason: str) -> None:
        super().__init__(f"{path}: {reason}", path=path, reason=reason)


def schema_bytes(filename: str) -> bytes:
    """One JSON Schema of ``schemas/``, read through importlib.resources (works from a wheel)."""
    return resources.files("mcsm.schemas").joinpath(filename).read_bytes()


# --------------------------------------------------------------------------------------------
# The state a recording reproduces
# --------------------------------------------------------------------------------------------

class MapState:
    """One named map plus what replay must reproduce: its sequence number and the recent acks.

    The live server and :func:`replay` both apply inputs through :meth:`apply`, so a replayed
    map is built by the same code path as the live one. Not thread-safe: one worker owns it.
    """

    def __init__(self, name: str, smap: StochasticMap, lru_size: int = DEFAULT_LRU,
                 id_ttl_s: float = DEFAULT_ID_TTL_S, *,
                 snapshot_every: int = DEFAULT_SNAPSHOT_EVERY,
                 snapshots_kept: int = DEFAULT_SNAPSHOTS_KEPT) -> None:
        self.name = name
        self.map = smap
        self.history = History(max(1, int(snapshot_every)), max(1, int(snapshots_kept)))
        self.history.start(smap, 0)
        self.last_changed: dict[str, wire.Verdict] = {}  # verdicts the last retract changed
        self.n_samples = int(smap.n_samples)
        self.seq = 0
        self.lru_size = int(lru_size)
        self.id_ttl_s = float(id_ttl_s)
        # request id -> (ack, request fingerprint, receive time ns), oldest first
        self._acks: OrderedDict[str, tuple[wire.Ack, str, int]] = OrderedDict()
        self.rejected = 0
        self.rejected_by_error: Counter[str] = Counter()
        self.verdicts: Counter[str] = Counter()  # applied updates per verdict status
        self._digest: tuple[int, str] | None = None

    def digest(self) -> str:
        """``map.state_digest()``, cached until the next applied operation."""
        if self._digest is None or self._digest[0] != self.seq:
            self._digest = (self.seq, self.map.state_digest())
        return self._digest[1]

    def _forget(self, now_ns: int) -> None:
        """Drop ids older than ``id_ttl_s`` and beyond ``lru_size`` (oldest first)."""
        cutoff = now_ns - int(self.id_ttl_s * 1e9)
        while self._acks:
            _, (_, _, t_ns) = next(iter(self._acks.items()))
            if t_ns >= cutoff and len(self._acks) <= self.lru_size:
                break
            self._acks.popitem(last=False)

    def lookup(self, request_id: str, fingerprint: str | None = None,
               now_ns: int | None = None) -> wire.Ack | None:
        """The original ack of an already applied request id (flagged duplicate), or None.

        With ``now_ns`` (the new request's receive time), ids older than ``id_ttl_s`` are
        forgotten first; without it only the count bound applies.

        Raises
        ------
        RequestIdReused
            If the id is remembered for a request with another ``fingerprint``.
        """
        if now_ns is not None:
            self._forget(now_ns)
        hit = self._acks.get(request_id)
        if hit is None:
            return None
        ack, fp, _ = hit
        if fingerprint is not None and fp and fp != fingerprint:
            raise RequestIdReused(request_id, ack.seq)
        return replace(ack, duplicate=True)

    def apply(self, op: str, req: Any, *, time_ns: int | None = None,
              fingerprint: str | None = None) -> wire.Ack:
        """Apply one decoded input received at ``time_ns``; returns its ack (seq ``seq + 1``).
        ``fingerprint`` is ``wire.request_fingerprint(op, req)`` if the caller has it.

        Raises
        ------
        McsmError
            Whatever the core refuses; the map and ``seq`` are then unchanged.
        """
        self.last_changed = {}
        if op == "update":
            r = self.map.update(req.a, req.b, req.samples, trusted=req.trusted)
            v = r.verdict
            verdict = wire.Verdict(v.status, v.nis, v.dof, v.threshold, v.reason, req.stamp_ns)
            ack = wire.Ack(req.request_id, self.seq + 1, op, r.kind, r.component,
                           frames_added=tuple(r.frames_added), verdict=verdict)
            self.verdicts[verdict.status] += 1
        elif op == "remove":
            rr = self.map.remove(req.frame)
            ack = wire.Ack(req.request_id, self.seq + 1, op, "remove", rr.component,
                           frames_removed=tuple(rr.frames_removed))
        elif op == "import":
            r = self.map.import_component(req.submap.to_core())
            ack = wire.Ack(req.request_id, self.seq + 1, op, r.kind, r.component,
                           frames_added=tuple(r.frames_added))
        elif op in ("retract", "reinstate"):
            ack = self._retract(op, req)
        else:
            raise McsmError(f"unknown operation {op!r}")
        self.seq = ack.seq
        t_ns = time.time_ns() if time_ns is None else int(time_ns)
        self._acks.pop(req.request_id, None)
        fp = fingerprint if fingerprint is not None else wire.request_fingerprint(op, req)
        self._acks[req.request_id] = (ack, fp, t_ns)
        self._forget(t_ns)
        self.history.record(ack.seq, op, req.request_id, req, ack.verdict, self.map)
        return ack

    def _retract(self, op: str, req: Any) -> wire.Ack:
        """Leave the update ``req.target`` out (retract) or put it back (reinstate): restore
        the last snapshot before it and apply every later input of the window again."""
        target = self.history.target(req.target, op == "retract")
        before = {e.request_id: e.verdict for e in self.history.log if e.op == "update"}
        smap, changed, commit = self.history.rebuild(target, op == "retract", self.map.threads)
        self.map = smap
        commit()
        for rid, v in changed.items():
            old = before.get(rid)
            if old is not None:
                self.verdicts[old.status] -= 1
            self.verdicts[v.status] += 1
            hit = self._acks.get(rid)
            if hit is not None:
                self._acks[rid] = (replace(hit[0], verdict=v), hit[1], hit[2])
        self.verdicts += Counter()  # drop zero counts
        self.last_changed = changed
        return wire.Ack(req.request_id, self.seq + 1, op, op, None, verdict=target.verdict)

    def verdict_of(self, request_id: str) -> wire.Ack:
        """The ack (with its current verdict) of a remembered request id.

        Raises
        ------
        InvalidOperation
            If the id is not remembered (never applied, or forgotten: ``--id-ttl-s``).
        """
        hit = self._acks.get(request_id)
        if hit is None:
            raise InvalidOperation(f"request {request_id!r} is unknown or forgotten")
        return hit[0]

    def count_rejected(self, err: McsmError) -> None:
        self.rejected += 1
        self.rejected_by_error[type(err).__name__] += 1


def decode_input(op: str, payload: bytes, n_samples: int) -> Any:
    """Decode a state-changing request with the wire codec (live and replay share this)."""
    if op == "update":
        return wire.decode_update(payload, n_samples)
    if op in ("retract", "reinstate"):
        return wire.decode_retract(payload)
    if op == "remove":
        return wire.decode_remove(payload)
    if op == "import":
        req = wire.decode_submap_request(payload, n_samples)
        if not isinstance(req, wire.SubmapImportRequest):
            raise McsmError("an export request cannot be recorded as an input")
        return req
    raise McsmError(f"unknown operation {op!r}")


# --------------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------------

class Recorder:
    """Append-only MCAP writer; every record is flushed to the OS before the call returns.

    Parameters
    ----------
    path : the new file (refused if it exists)
    fsync : also ``os.fsync`` after each input (survives power loss; ~4 ms per message here)
    """

    def __init__(self, path: str | os.PathLike[str], *, fsync: bool = False) -> None:
        self.path = Path(path)
        if self.path.exists():
            raise RecordingError(str(self.path), "exists; refusing to overwrite a recording")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._fh: BinaryIO = open(self.path, "xb")  # noqa: SIM115 - closed in close()
        self._fsync = fsync
        self._w = Writer(self._fh, use_chunking=False, enable_crcs=True)
        self._w.start(profile="", library=f"mcsm {__version__}")
        self._channels: dict[str, int] = {}
        for topic, (name, filename) in _SCHEMAS.items():
            sid = self._w.register_schema(name, "jsonschema", schema_bytes(filename))
            self._channels[topic] = self._w.register_channel(topic, "msgpack", sid)
        self._w.add_metadata("mcsm", {"software": f"mcsm {__version__}",
                                      "format": "mcsm recording v1"})
        self._w.flush()
        self.n_inputs = 0
        self.closed = False

    def _add(self, topic: str, obj: dict[str, Any], log_time_ns: int, seq: int) -> None:
        data = wire.pack({"v": wire.VERSION, **obj})
        self._w.add_message(self._channels[topic], log_time=int(log_time_ns), data=data,
                            publish_time=time.time_ns(), sequence=int(seq) & 0xFFFFFFFF)

    def _flush(self, sync: bool) -> None:
        self._w.flush()
        if sync:
            os.fsync(self._fh.fileno())

    def config(self, state: MapState, checkpoint_every: int, server_id: str = "",
               restored_from: str | None = None) -> None:
        """Record the options that rebuild ``state``'s empty map (once per map, first)."""
        now = time.time_ns()
        self._add(TOPIC_CONFIG, {"map": state.name, "options": state.map.options(),
                                 "checkpoint_every": int(checkpoint_every), "time_ns": now,
                                 "snapshot_every": state.history.snapshot_every,
                                 "snapshots_kept": state.history.snapshots_kept,
                                 "server_id": server_id, "restored_from": restored_from,
                                 "software": f"mcsm {__version__}"}, now, 0)
        self._flush(self._fsync)

    def input(self, op: str, map_name: str, seq: int, recv_ns: int, sender: str,
              request_id: str, payload: bytes) -> None:
        """Record one applied input and flush it (call before acknowledging)."""
        self._add(INPUT_TOPICS[op], {"map": map_name, "seq": seq, "recv_ns": recv_ns,
                                     "sender": sender, "id": request_id,
                                     "request": bytes(payload)}, recv_ns, seq)
        self._flush(self._fsync)
        self.n_inputs += 1

    def checkpoint(self, map_name: str, seq: int, digest: str, reason: str) -> None:
        self._add(TOPIC_CHECKPOINT, {"map": map_name, "seq": seq, "digest": digest,
                                     "reason": reason}, time.time_ns(), seq)
        self._flush(self._fsync)

    def close(self) -> None:
        """Write the summary and footer and close the file (idempotent)."""
        if self.closed:
            return
        self.closed = True
        try:
            self._w.finish()
            self._fh.flush()
            os.fsync(self._fh.fileno())
        finally:
            self._fh.close()


# --------------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------------

@dataclass
class RecordItem:
    topic: str
    data: dict[str, Any]
    log_time_ns: int


class RecordingReader:
    """Stream the records of a recording, complete or cut short (SIGKILL, full disk).

    Iterating yields :class:`RecordItem` in file order. Afterwards ``complete`` tells whether
    the file ended cleanly (a footer was read) and ``tail_error`` why reading stopped early.

    Raises
    ------
    RecordingError
        If the file is not an MCAP file, or a record does not decode as an mcsm record.
    """

    def __init__(self, path: str | os.PathLike[str],
                 progress: Callable[[int, int], None] | None = None) -> None:
        self.path = Path(path)
        self.size = self.path.stat().st_size
        self.progress = progress
        self.complete = False
        self.tail_error: str | None = None
        self.library = ""
        self.n_messages = 0

    def __iter__(self) -> Iterator[RecordItem]:
        channels: dict[int, str] = {}
        with open(self.path, "rb") as fh:
            reader = StreamReader(fh, record_size_limit=MAX_RECORD_BYTES)
            records = iter(reader.records)
            last_report = 0.0
            try:
                header = next(records)
            except (McapError, EOFError, ValueError, struct.error, StopIteration) as exc:
                raise RecordingError(str(self.path), f"not an MCAP file ({type(exc).__name__})"
                                     ) from None
            self.library = str(getattr(header, "library", ""))
            while True:
                try:
                    rec = next(records)
                except StopIteration:
                    break
                except (McapError, EOFError, ValueError, struct.error) as exc:
                    self.tail_error = (f"{type(exc).__name__} at byte {fh.tell()} of "
                                       f"{self.size}: {exc}")
                    break
                if isinstance(rec, Schema):
                    continue
                if isinstance(rec, Channel):
                    channels[rec.id] = rec.topic
                elif isinstance(rec, Message):
                    topic = channels.get(rec.channel_id)
                    if topic is None:
                        raise RecordingError(str(self.path),
                                             f"message on undeclared channel {rec.channel_id}")
                    try:
                        data = wire.unpack(rec.data, max_bytes=MAX_RECORD_BYTES)
                    except McsmError as exc:
                        raise RecordingError(str(self.path),
                                             f"undecodable record on {topic}: {exc}") from None
                    self.n_messages += 1
                    yield RecordItem(topic, data, int(rec.log_time))
                elif isinstance(rec, (DataEnd, Footer)):
                    if isinstance(rec, Footer):
                        self.complete = True
                        break
                if self.progress is not None:
                    now = time.monotonic()
                    if now - last_report > 0.1:
                        last_report = now
                        self.progress(fh.tell(), self.size)
            if self.progress is not None:
                self.progress(self.size if self.complete else fh.tell(), self.size)


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
    divergence: str | None = None
    complete: bool = False
    tail_error: str | None = None
    first_time_ns: int | None = None
    last_time_ns: int | None = None
    elapsed_s: float = 0.0
    library: str = ""

    @property
    def identical(self) -> bool:
        return self.divergence is None

    def final_digests(self) -> dict[str, str]:
        return {name: st.map.state_digest() for name, st in self.states.items()}


def replay(path: str | os.PathLike[str], *, sink: Recorder | None = None,
           progress: Callable[[int, int], None] | None = None,
           lru_size: int = DEFAULT_LRU, server_id: str = "",
           stop_after: int | None = None) -> ReplayReport:
    """Rebuild every map of a recording and check its digests at every checkpoint.

    Parameters
    ----------
    path : the recording (complete or truncated)
    sink : if given, every config, input and checkpoint is written again into this recorder
        (used by ``mcsm serve --restore``: the new file replays on its own)
    progress : called with (bytes read, file size) at most ten times a second
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
    rep = ReplayReport(path=str(path))
    reader = RecordingReader(path, progress)
    for item in reader:
        if stop_after is not None and rep.n_inputs >= stop_after:
            break
        d = item.data
        if rep.first_time_ns is None:
            rep.first_time_ns = item.log_time_ns
        rep.last_time_ns = item.log_time_ns
        name = d.get("map")
        if not isinstance(name, str):
            raise RecordingError(str(path), f"record on {item.topic} without a map name")
        if item.topic == TOPIC_CONFIG:
            if name in rep.states:
                continue  # a map's config is written once; ignore repeats
            try:
                smap = StochasticMap.from_options(dict(d["options"]))
            except (McsmError, KeyError, TypeError, ValueError) as exc:
                raise RecordingError(str(path), f"bad options for map {name!r}: {exc}"
                                     ) from None
            st = MapState(name, smap, lru_size,
                          snapshot_every=int(d.get("snapshot_every", DEFAULT_SNAPSHOT_EVERY)),
                          snapshots_kept=int(d.get("snapshots_kept", DEFAULT_SNAPSHOTS_KEPT)))
            rep.states[name] = st
            rep.configs[name] = dict(d)
            if sink is not None:
                sink.config(st, int(d.get("checkpoint_every", 100)), server_id=server_id,
                            restored_from=str(path))
            continue
        st_or_none = rep.states.get(name)
        if st_or_none is None:
            raise RecordingError(str(path), f"record for map {name!r} before its config")
        st = st_or_none
        if item.topic == TOPIC_CHECKPOINT:
            cp = Checkpoint(name, int(d["seq"]), str(d["digest"]), str(d.get("reason", "")))
            rep.checkpoints.append(cp)
            if cp.seq != st.seq:
                rep.divergence = (f"map {name!r}: checkpoint at seq {cp.seq} but replay is at "
                                  f"seq {st.seq}")
                break
            got = st.digest()
            if got != cp.digest:
                rep.divergence = (f"map {name!r}: digest differs at seq {cp.seq} "
                                  f"(recorded {cp.digest[:16]}..., replayed {got[:16]}...)")
                break
            rep.checkpoints_ok += 1
            if sink is not None:
                sink.checkpoint(name, cp.seq, cp.digest, cp.reason)
            continue
        op = TOPIC_OPS.get(item.topic)
        if op is None:
            log.warning("%s: ignoring records on unknown topic %s", path, item.topic)
            continue
        seq = int(d["seq"])
        if seq != st.seq + 1:
            rep.divergence = (f"map {name!r}: input seq {seq} follows seq {st.seq} "
                              "(gap or reordering)")
            break
        try:
            req = decode_input(op, bytes(d["request"]), st.n_samples)
            ack = st.apply(op, req, time_ns=int(d["recv_ns"]))
        except McsmError as exc:
            rep.divergence = (f"map {name!r}: input seq {seq} ({op}) was refused on replay: "
                              f"{type(exc).__name__}: {exc}")
            break
        rep.n_inputs += 1
        rep.ops[op] += 1
        if sink is not None:
            sink.input(op, name, ack.seq, int(d["recv_ns"]), str(d.get("sender", "")),
                       str(d.get("id", "")), bytes(d["request"]))
    rep.complete = reader.complete
    rep.tail_error = reader.tail_error
    rep.library = reader.library
    rep.elapsed_s = time.perf_counter() - t0
    return rep


def progress_bar(stream: Any = None, width: int = 30) -> Callable[[int, int], None]:
    """A text progress bar over bytes read, drawn on stderr with ``\\r`` (caller ends the line)."""
    out = stream if stream is not None else sys.stderr

    def draw(done: int, total: int) -> None:
        frac = 1.0 if total <= 0 else min(1.0, done / total)
        n = int(round(frac * width))
        out.write(f"\r[{'#' * n}{'.' * (width - n)}] {100 * frac:5.1f}% "
                  f"{done / 1e6:.1f}/{total / 1e6:.1f} MB")
        out.flush()

    return draw
