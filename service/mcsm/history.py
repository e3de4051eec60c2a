"""Taking a constraint back: state snapshots and the recent input log of one map.

An accepted constraint cannot be subtracted from an ensemble map: every later update used the
samples it moved. The exact way back is to restore a state from before it and apply every
later input again without it; deterministic replay makes that bit-identical to a map that
never had it (measured in docs/outliers.md). :class:`History` keeps,
for one map, a snapshot every ``snapshot_every`` operations (the last ``snapshots_kept`` of
them, in memory) and the decoded inputs since the oldest kept snapshot: the *retract window*.

A retraction or reinstatement is itself an applied, recorded operation with its own sequence
number, so replay (which applies the same operations through the same code) reproduces it.
Inputs re-applied after a retraction are gated again: their verdicts may change (a true loop
closure rejected because of a wrong one before it can now be accepted); :meth:`rebuild`
returns which did.

The window is bounded twice: by count (``--snapshots-kept`` snapshots taken every
``--snapshot-every`` operations) and by bytes (``--retract-window-bytes``: the snapshots' arrays
plus the logged requests' arrays). A snapshot is also taken once the inputs logged since the
last one reach ``max_bytes / snapshots_kept``, and the oldest snapshots (with the inputs before
the next one) are dropped while the window is over its budget, so with big requests the window
holds between about (S-1)/S and all of the budget; a map whose own snapshot is larger than the
budget has no window until it shrinks. Both bounds are functions of the applied inputs and of
the options recorded in the map's config, so replay reproduces the same window, and a
retraction refused live is refused on replay.

Nothing here touches the recording: these snapshots live in memory. The recording holds its
own, less frequent ones (``mcsm serve --disk-snapshot-every``), from which ``--restore``
starts; the retract window of a restored map begins there, and so does that of a map whose
recording was split (a new file starts with a snapshot, ``mcsm serve --split-size``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, fields, is_dataclass, replace
from typing import Any

import numpy as np

from mcsm import ops, wire
from mcsm.core.smap import StochasticMap
from mcsm.deferral import Deferral, DeferState
from mcsm.errors import InvalidOperation, McsmError

DEFAULT_SNAPSHOT_EVERY = 100
"""Operations between two snapshots of a map (``mcsm serve --snapshot-every``)."""
DEFAULT_SNAPSHOTS_KEPT = 5
"""Snapshots kept per map (``--snapshots-kept``): the retract window is the inputs since the
oldest one, between (kept - 1) and kept times ``snapshot_every`` operations."""
DEFAULT_WINDOW_BYTES = 256 * 1024 * 1024
"""Bytes the retract window of one map holds at most (``--retract-window-bytes``): its
snapshots' arrays plus its logged requests' arrays."""


def nbytes(obj: Any) -> int:
    """Bytes of the arrays (and byte strings) in ``obj``: a decoded request or a map snapshot,
    walked through dataclasses, dicts, lists and tuples (the snapshot's layout is opaque here).
    A deterministic function of the object, so replay computes the same window."""
    if isinstance(obj, np.ndarray):
        return int(obj.nbytes)
    if isinstance(obj, (bytes, bytearray, memoryview)):
        return len(obj)
    if isinstance(obj, dict):
        return sum(nbytes(v) for v in obj.values())
    if isinstance(obj, (list, tuple)):
        return sum(nbytes(v) for v in obj)
    if is_dataclass(obj) and not isinstance(obj, type):
        return sum(nbytes(getattr(obj, f.name)) for f in fields(obj))
    return 0


@dataclass
class Logged:
    """One applied input of the window: its request, sequence number and current verdict.

    With ``payload`` (the request's bytes as received and recorded) the decoded request is not
    kept: :attr:`req` decodes it again when a retraction needs it, so the window holds each
    input once. ``nbytes`` is the size of the decoded request's arrays either way (the same on
    every server and in replay)."""

    seq: int
    op: str
    request_id: str
    decoded: Any
    verdict: wire.Verdict | None = None
    retracted: bool = False
    nbytes: int = 0
    payload: bytes | None = None
    n_samples: int = 0

    @property
    def req(self) -> Any:
        """The decoded request (decoded again from ``payload`` when not kept)."""
        if self.decoded is not None or self.payload is None:
            return self.decoded
        return ops.decode_input(self.op, self.payload, self.n_samples)


Snapshot = tuple[int, dict[str, Any], "DeferState | None", int]
"""(seq, map snapshot, deferral state at that seq (None without --gate-defer), its bytes)"""


@dataclass
class History:
    snapshot_every: int = DEFAULT_SNAPSHOT_EVERY
    snapshots_kept: int = DEFAULT_SNAPSHOTS_KEPT
    #: bytes of the window at most (None: unbounded, as recordings made before the bound)
    max_bytes: int | None = None
    snapshots: list[Snapshot] = field(default_factory=list)
    log: list[Logged] = field(default_factory=list)
    by_id: dict[str, Logged] = field(default_factory=dict)
    #: the seq below which updates fell out of the window (0: nothing fell out yet)
    dropped_before: int = 0

    @property
    def held_bytes(self) -> int:
        """Bytes the window holds now (snapshots' and logged requests' arrays)."""
        return sum(s[3] for s in self.snapshots) + sum(e.nbytes for e in self.log)

    def start(self, smap: StochasticMap, seq: int, defer: DeferState | None = None) -> None:
        """The first snapshot (the map and its deferral state as they are at ``seq``)."""
        snap = smap.snapshot()
        self.snapshots = [(seq, snap, defer, nbytes(snap))]
        self.log, self.by_id = [], {}
        self.dropped_before = seq
        self._trim()

    def _due(self, seq: int) -> bool:
        """Whether a snapshot is taken after operation ``seq``: every ``snapshot_every``
        operations, and once the log since the last snapshot holds ``max_bytes / kept``."""
        if seq % self.snapshot_every == 0:
            return True
        if self.max_bytes is None or not self.snapshots:
            return False
        last = self.snapshots[-1][0]
        since = sum(e.nbytes for e in self.log if e.seq > last)
        return since >= self.max_bytes // max(1, self.snapshots_kept)

    def record(self, seq: int, op: str, request_id: str, req: Any,
               verdict: wire.Verdict | None, smap: StochasticMap,
               defer: DeferState | None = None, payload: bytes | None = None) -> None:
        """Log an applied input (after the map changed) and take the scheduled snapshot;
        with ``payload`` (its bytes), the window keeps those instead of the decoded request."""
        if not self.snapshots:  # no window (the map alone is over the budget)
            self.dropped_before = seq
            if seq % self.snapshot_every == 0:
                self.start(smap, seq, defer)
            return
        entry = Logged(seq, op, request_id, None if payload is not None else req, verdict,
                       nbytes=nbytes(req), payload=None if payload is None else bytes(payload),
                       n_samples=int(smap.n_samples))
        self.log.append(entry)
        if ops.get(op).change is not None:  # an input (not a retract): a possible target
            self.by_id[request_id] = entry
        if self._due(seq):
            snap = smap.snapshot()
            self.snapshots.append((seq, snap, defer, nbytes(snap)))
        self._trim()

    def decided(self, verdicts: dict[str, wire.Verdict]) -> None:
        """Held closures (``--gate-defer``) decided by a later input: their final verdicts."""
        for rid, v in verdicts.items():
            e = self.by_id.get(rid)
            if e is not None:
                e.verdict = v

    def _over(self) -> bool:
        return self.max_bytes is not None and self.held_bytes > self.max_bytes

    def _trim(self) -> None:
        while self.snapshots and (len(self.snapshots) > max(1, self.snapshots_kept)
                                  or (len(self.snapshots) > 1 and self._over())):
            self.snapshots.pop(0)
            self._drop_log(self.snapshots[0][0])
        if self.snapshots and self._over():  # the last snapshot and its log alone are too big
            self.dropped_before = max(self.dropped_before, self.snapshots[-1][0],
                                      self.log[-1].seq if self.log else 0)
            self.snapshots, self.log, self.by_id = [], [], {}
        elif self.snapshots:
            self._drop_log(self.snapshots[0][0])

    def _drop_log(self, oldest: int) -> None:
        """Forget the logged inputs up to seq ``oldest`` (the window's first snapshot)."""
        self.dropped_before = max(self.dropped_before, oldest)
        keep = [e for e in self.log if e.seq > oldest]
        dropped = len(self.log) - len(keep)
        if dropped:
            for e in self.log[:dropped]:
                if self.by_id.get(e.request_id) is e:
                    del self.by_id[e.request_id]
            self.log = keep

    @property
    def window_start(self) -> int:
        """Inputs with a sequence number above this can be retracted or reinstated (with no
        window at all, none can: the last seq logged)."""
        return self.snapshots[0][0] if self.snapshots else self.dropped_before

    def target(self, request_id: str, retract: bool) -> Logged:
        """The window's update ``request_id``, checked for a retraction or a reinstatement (of
        a retracted update, or of one the gate rejected: it goes in as trusted).

        Raises
        ------
        InvalidOperation
            Not an update of the window, or already in the asked state.
        """
        e = self.by_id.get(request_id)
        if e is None:
            raise InvalidOperation(
                f"request {request_id!r} is not an update of the retract window (the inputs "
                f"after seq {self.window_start}; {self.reach()})")
        if not ops.get(e.op).retractable:
            raise InvalidOperation(f"request {request_id!r} is a {e.op}: only updates can be "
                                   "retracted or reinstated")
        if e.verdict is not None and e.verdict.status == "pending":
            raise InvalidOperation(
                f"request {request_id!r} is pending (held by --gate-defer until a second "
                "closure agrees or it expires): retract or reinstate it once it is decided")
        if retract and e.retracted:
            raise InvalidOperation(f"request {request_id!r} is already retracted")
        rejected = e.verdict is not None and e.verdict.status == "rejected"
        if not retract and not (e.retracted or rejected):
            raise InvalidOperation(f"request {request_id!r} is neither retracted nor rejected")
        return e

    def reach(self) -> str:
        """What bounds the window, in words (for refusals)."""
        budget = ("" if self.max_bytes is None
                  else f" and --retract-window-bytes {self.max_bytes}")
        none = ("; the map alone is larger than the byte budget, so no update can be "
                "retracted until it shrinks" if not self.snapshots else "")
        return (f"the window holds --snapshots-kept {self.snapshots_kept} snapshots taken every "
                f"--snapshot-every {self.snapshot_every} operations{budget}{none}")

    def rebuild(self, target: Logged, retract: bool, threads: int | None,
                deferral: Deferral | None = None, device: object = "cpu"
                ) -> tuple[StochasticMap, dict[str, wire.Verdict], Callable[[], None],
                           Deferral | None]:
        """The map with ``target`` left out (``retract``) or put back, from the last snapshot
        before it plus every later input of the window; the verdicts that changed; a
        function that commits the new window (snapshots, flags, verdicts) once the caller
        has swapped the map in; and the deferral policy (``--gate-defer``) in its new state,
        having decided every later update again from its state at that snapshot. Raises
        nothing that leaves a half-changed window."""
        base = [s for s in self.snapshots if s[0] < target.seq]
        retake = {s[0] for s in self.snapshots if s[0] > base[-1][0]}
        seq0, snap, defer0, _ = base[-1]
        smap = StochasticMap.from_snapshot(snap, threads=threads, device=device)
        dfr = None if deferral is None else deferral.copy(defer0 or DeferState())
        new_snaps = list(base)
        verdicts: dict[str, wire.Verdict | None] = {}  # request id -> its verdict now
        retracted: dict[int, bool] = {}
        for e in self.log:
            if e.seq <= seq0:
                continue
            left_out = (e.retracted and e is not target) or (e is target and retract)
            # reinstated updates (this one, or earlier ones) go in as trusted, every time
            forced = not left_out and (e is target or (
                e.verdict is not None and e.verdict.status == "reinstated"))
            verdict = e.verdict
            op = ops.get(e.op)
            if op.change is not None:
                if left_out:
                    verdict = _with_status(verdict, "retracted")
                else:
                    try:  # a reinstated update goes back in whatever the gate says
                        if e.op == "update" and dfr is not None:
                            out = dfr.update(smap, e.seq, e.req, trusted=forced)
                            verdict = out.verdict
                            verdicts.update(out.decided)
                        else:
                            verdict = op.change(smap, e.req, trusted=forced).verdict
                    except McsmError as exc:  # it no longer applies (its frame is gone)
                        verdict = wire.Verdict("rejected", None, 0, None,
                                               f"no longer applies: {type(exc).__name__}")
                    if forced:
                        verdict = _with_status(verdict, "reinstated")
            verdicts[e.request_id] = verdict
            retracted[e.seq] = left_out if op.retractable else e.retracted
            if e.seq in retake:  # at the same seqs as before: the window stays where it was
                s1 = smap.snapshot()
                new_snaps.append((e.seq, s1, None if dfr is None else dfr.state, nbytes(s1)))
        now = {e.request_id: e.verdict for e in self.log if ops.get(e.op).retractable}
        in_log = {e.request_id for e in self.log}
        # the updates whose verdict changed, and held closures from before the log that were
        # decided again (the caller compares those with their acks)
        changed = {rid: v for rid, v in verdicts.items() if v is not None
                   and (v != now[rid] if rid in now else rid not in in_log)}

        def commit() -> None:
            for e in self.log:
                if e.seq in retracted:
                    e.retracted = retracted[e.seq]
                if e.request_id in verdicts and ops.get(e.op).retractable:
                    e.verdict = verdicts[e.request_id]
            self.snapshots = new_snaps
            self._trim()

        return smap, changed, commit, dfr


def _with_status(v: wire.Verdict | None, status: str) -> wire.Verdict:
    return wire.Verdict(status) if v is None else replace(v, status=status)


__all__ = ["History", "Logged", "DEFAULT_SNAPSHOT_EVERY", "DEFAULT_SNAPSHOTS_KEPT",
           "DEFAULT_WINDOW_BYTES", "nbytes"]
