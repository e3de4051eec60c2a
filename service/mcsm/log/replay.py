"""Deterministic replay: :func:`replay` applies a recording's inputs through
:class:`~mcsm.map.state.MapState` (the code the live server runs), from its start or from a
snapshot, and checks every checkpoint; :class:`ReplayReport` says what it found."""

from __future__ import annotations

import logging
import os
import time
from collections import Counter
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcsm import wire
from mcsm.core import ARITHMETIC_VERSION
from mcsm.core.smap import StochasticMap
from mcsm.errors import McsmError
from mcsm.log.reader import RecordingReader
from mcsm.log.topics import (
    INPUT_TOPICS,
    LEGACY_ARITHMETIC_VERSION,
    TOPIC_CHECKPOINT,
    TOPIC_CONFIG,
    TOPIC_OPS,
    TOPIC_SNAPSHOT,
    RecordingError,
    RecordItem,
    decode_input,
)
from mcsm.log.writer import Recorder
from mcsm.map.carry import decode_ids, decode_snapshot, decode_window
from mcsm.map.deferral import DeferOptions, DeferState
from mcsm.map.history import DEFAULT_SNAPSHOT_EVERY, DEFAULT_SNAPSHOTS_KEPT
from mcsm.map.state import DEFAULT_ID_TTL_S, DEFAULT_LRU, MapState

log = logging.getLogger(__name__)


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
                 progress: Callable[[int, int], None] | None = None,
                 edges: bool | Callable[[dict[str, Any]], bool] = True) -> None:
        self.paths = paths
        self.edges = edges
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

            reader = RecordingReader(path, report if self.progress is not None else None,
                                     edges=self.edges)
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
        for item in RecordingReader(paths[k], edges=False):  # snapshots' edges not kept
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
    order: :func:`mcsm.log.recset.resolve`) and check its digests at every checkpoint and
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

    def load_edges(head: dict[str, Any]) -> bool:
        """Whether a chunked snapshot's edges are needed: only where replay starts from it
        (the condition below); the others are verified by their digest alone."""
        st0 = rep.states.get(str(head.get("map")))
        seq0 = int(head.get("seq", -1))
        return st0 is None or seq0 == start.get(st0.name) or st0.seq == 0 < seq0

    reader = _Chain(paths[first:], progress, edges=load_edges)
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
    deferral state, remembered ids (when recorded) and retract window (when carried). The
    record's ``state`` is dropped afterwards (its arrays are the size of the map).

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
    d["state"] = None  # the record's copy of the edges: freed before the digest check
    del snap
