"""The state a recording reproduces: one named map, its sequence number, the request ids it
remembers (idempotency), its verdict counts, its retract window (:mod:`mcsm.history`) and,
with ``--gate-defer``, its deferral policy (:mod:`mcsm.deferral`).

The live server and replay (:func:`mcsm.recording.replay`) both apply inputs through
:meth:`MapState.apply`, so a replayed map is built by the same code path as the live one.
"""

from __future__ import annotations

import time
from collections import Counter
from dataclasses import replace
from typing import Any

from mcsm import ops, wire
from mcsm.core.smap import StochasticMap
from mcsm.deferral import DeferOptions, Deferral, DeferState
from mcsm.errors import InvalidOperation, McsmError, RequestIdReused
from mcsm.history import DEFAULT_SNAPSHOT_EVERY, DEFAULT_SNAPSHOTS_KEPT, History
from mcsm.idmemory import IdColumns, IdMemory

DEFAULT_LRU = 100_000
"""Request ids (with their acks) each map remembers at most (about 25 MB at most:
:mod:`mcsm.idmemory`)."""
DEFAULT_ID_TTL_S = 600.0
"""Seconds a request id is remembered (ten minutes: a server restart takes 1-8 s)."""



class MapState:
    """One named map plus what replay must reproduce: its sequence number and the recent acks.

    The live server and :func:`replay` both apply inputs through :meth:`apply`, so a replayed
    map is built by the same code path as the live one. Not thread-safe: one worker owns it.
    """

    def __init__(self, name: str, smap: StochasticMap, lru_size: int = DEFAULT_LRU,
                 id_ttl_s: float = DEFAULT_ID_TTL_S, *,
                 snapshot_every: int = DEFAULT_SNAPSHOT_EVERY,
                 snapshots_kept: int = DEFAULT_SNAPSHOTS_KEPT,
                 gate_defer: DeferOptions | None = None,
                 retract_window_bytes: int | None = None) -> None:
        self.name = name
        self.map = smap
        # --gate-defer: first closures of a revisit held until a second one agrees
        self.deferral = None if gate_defer is None else Deferral(gate_defer, smap.gate)
        # --retract-window-bytes (None: unbounded, as in recordings made before the bound)
        self.history = History(max(1, int(snapshot_every)), max(1, int(snapshots_kept)),
                               None if retract_window_bytes is None
                               else max(0, int(retract_window_bytes)))
        self.history.start(smap, 0, self._defer_state())
        # verdicts the last input changed: a retract's re-gated inputs, a decided held closure
        self.last_changed: dict[str, wire.Verdict] = {}
        self.n_samples = int(smap.n_samples)
        self.seq = 0
        self.lru_size = int(lru_size)
        self.id_ttl_s = float(id_ttl_s)
        # request id -> (ack, request fingerprint, receive time ns), oldest first
        self._acks = IdMemory(self.lru_size)
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
        while True:
            t_ns = self._acks.oldest_time()
            if t_ns is None or (t_ns >= cutoff and len(self._acks) <= self.lru_size):
                break
            self._acks.pop_oldest()

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
              fingerprint: str | None = None, payload: bytes | None = None) -> wire.Ack:
        """Apply one decoded input received at ``time_ns``; returns its ack (seq ``seq + 1``).
        ``fingerprint`` is ``ops.fingerprint(op, req)`` if the caller has it; ``payload`` (the
        request's bytes, as recorded) lets the retract window keep those instead of the
        decoded request, and a split recording carry the window (:meth:`Recorder.snapshot`).

        Raises
        ------
        McsmError
            Whatever the core refuses; the map and ``seq`` are then unchanged.
        """
        self.last_changed = {}
        operation = ops.get(op)
        if op == "update" and self.deferral is not None:
            out = self.deferral.update(self.map, self.seq + 1, req)
            verdict, r = out.verdict, out.result
            if r is None:  # held (pending), or refused after the held one went in
                ack = wire.Ack(req.request_id, self.seq + 1, op, verdict.status,
                               self.map.root(req.a), verdict=verdict)
            else:
                ack = wire.Ack(req.request_id, self.seq + 1, op, r.kind, r.component,
                               frames_added=tuple(r.frames_added), verdict=verdict,
                               relin=None if r.relin is None else r.relin.to_dict())
            self.verdicts[verdict.status] += 1
            for decided in out.decided.values():  # a held closure decided now: was pending
                self.verdicts["pending"] -= 1
                self.verdicts[decided.status] += 1
            self.verdicts += Counter()  # drop zero counts
            self._set_verdicts(out.decided)
            self.history.decided(out.decided)
            self.last_changed = dict(out.decided)
        elif operation.retract is not None:
            ack = self._retract(op, req, operation.retract)
        elif operation.change is not None:
            c = operation.change(self.map, req)
            ack = wire.Ack(req.request_id, self.seq + 1, op, c.kind, c.component,
                           frames_added=c.frames_added, frames_removed=c.frames_removed,
                           verdict=c.verdict, relin=c.relin)
            if c.verdict is not None:
                self.verdicts[c.verdict.status] += 1
        else:
            raise McsmError(f"{op!r} changes nothing: it is answered, not applied")
        self.seq = ack.seq
        t_ns = time.time_ns() if time_ns is None else int(time_ns)
        fp = fingerprint if fingerprint is not None else ops.fingerprint(op, req)
        self._acks.put(req.request_id, ack, fp, t_ns)
        self._forget(t_ns)
        self.history.record(ack.seq, op, req.request_id, req, ack.verdict, self.map,
                            self._defer_state(), payload)
        return ack

    def _defer_state(self) -> DeferState | None:
        return None if self.deferral is None else self.deferral.state

    def _set_verdicts(self, verdicts: dict[str, wire.Verdict]) -> None:
        """The remembered acks of these request ids now carry these verdicts."""
        for rid, v in verdicts.items():
            hit = self._acks.get(rid)
            if hit is not None:
                self._acks.update(rid, replace(hit[0], verdict=v))

    def _retract(self, op: str, req: Any, retract: bool) -> wire.Ack:
        """Leave the update ``req.target`` out (``retract``) or put it back (reinstate):
        restore the last snapshot before it and apply every later input of the window again."""
        if req.target not in self.history.by_id:
            hit = self._acks.get(req.target)
            if hit is not None and hit[0].seq <= self.history.window_start:
                raise InvalidOperation(
                    f"request {req.target!r} (seq {hit[0].seq}) fell out of the retract "
                    f"window, which now holds the inputs after seq "
                    f"{self.history.window_start} ({self.history.reach()}): it can no longer "
                    "be retracted or reinstated")
        target = self.history.target(req.target, retract)
        before: dict[str, wire.Verdict | None] = {
            e.request_id: e.verdict for e in self.history.log if ops.get(e.op).retractable}
        held = None if self.deferral is None else self.deferral.pending_id()
        smap, changed, commit, dfr = self.history.rebuild(
            target, retract, self.map.threads, self.deferral,
            device="cpu" if self.map.backend is None else self.map.backend)
        self.map = smap
        self.deferral = dfr
        commit()
        for rid in list(changed):
            old = before.get(rid)
            if rid not in before:  # a held closure from before the window's log
                hit = self._acks.get(rid)
                old = hit[0].verdict if hit is not None else None
                if old is None and rid == held:
                    old = wire.Verdict("pending")
                if old == changed[rid]:
                    del changed[rid]
                    continue
            if old is not None:
                self.verdicts[old.status] -= 1
            self.verdicts[changed[rid].status] += 1
        self._set_verdicts(changed)
        self.verdicts += Counter()  # drop zero counts
        self.last_changed = changed
        return wire.Ack(req.request_id, self.seq + 1, op, op, None, verdict=target.verdict)

    def restore(self, seq: int, smap: StochasticMap, verdicts: dict[str, int],
                defer: DeferState | None = None, ids: list[list[Any]] | None = None) -> None:
        """Continue from a recorded snapshot: the map as it was after operation ``seq``, the
        deferral state then (``--gate-defer``: the held closure, if any) and, when the snapshot
        holds them, the request ids remembered then (:meth:`export_ids` rows; they replace
        the ids remembered so far)."""
        smap.threads = self.map.threads
        self.map, self.seq = smap, int(seq)
        if ids is not None:
            self.import_ids(ids, replace_all=True)
        self.verdicts = Counter({str(k): int(v) for k, v in verdicts.items()})
        if self.deferral is not None:
            self.deferral = self.deferral.copy(defer or DeferState())
            h = self.deferral.state.held
            if h is not None:  # remembered without its ack (or not at all): it is pending
                v = wire.Verdict("pending", reason="held by --gate-defer",
                                 stamp_ns=h.req.stamp_ns)
                hit = self._acks.get(h.request_id)
                if hit is None:  # its input is not in this file (a restored server's file)
                    self._acks.put(h.request_id, wire.Ack(h.request_id, h.seq, "update",
                                                          "pending", None, verdict=v),
                                   ops.fingerprint("update", h.req), time.time_ns())
                else:
                    self._acks.update(h.request_id, replace(hit[0], verdict=v))
        self.history.start(smap, self.seq, self._defer_state())
        self._digest = None

    def remember(self, op: str, req: Any, seq: int, time_ns: int) -> None:
        """Remember the id of an input applied before a snapshot replay started from (so a
        retry of it is not applied twice); its ack is not known, only its seq and op."""
        ack = wire.Ack(req.request_id, int(seq), op, "restored", None)
        self._acks.put(req.request_id, ack, ops.fingerprint(op, req), int(time_ns))
        self._forget(int(time_ns))

    def export_ids(self) -> list[list[Any]]:
        """The remembered request ids, oldest first, as ``[id, seq, op, fingerprint,
        time_ns]`` rows (a standby that starts from a snapshot imports them, so a retry of an
        input applied before that snapshot is still recognised after a takeover)."""
        return [[rid, ack.seq, ack.op, fp, t] for rid, (ack, fp, t) in self._acks.items()]

    def id_columns(self) -> IdColumns:
        """The remembered ids, oldest first, as columns (:meth:`IdMemory.columns`): what a
        recorded snapshot holds (:func:`mcsm.carry.encode_ids`)."""
        return self._acks.columns()

    def import_ids(self, rows: list[Any], *, replace_all: bool = False) -> None:
        """Remember the ids of :meth:`export_ids` (their acks say ``restored``); with
        ``replace_all``, instead of the ids remembered so far."""
        if replace_all:
            self._acks.clear()
        for row in rows:
            rid, seq, op, fp, t_ns = row
            self._acks.put(str(rid), wire.Ack(str(rid), int(seq), str(op), "restored", None),
                           str(fp), int(t_ns))
        while len(self._acks) > self.lru_size:
            self._acks.pop_oldest()

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


__all__ = ["MapState", "DEFAULT_LRU", "DEFAULT_ID_TTL_S"]
