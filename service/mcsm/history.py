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

Nothing here touches the recording: these snapshots live in memory. The recording holds its
own, less frequent ones (``mcsm serve --disk-snapshot-every``), from which ``--restore``
starts; the retract window of a restored map begins there.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

from mcsm import ops, wire
from mcsm.core.smap import StochasticMap
from mcsm.deferral import Deferral, DeferState
from mcsm.errors import InvalidOperation, McsmError

DEFAULT_SNAPSHOT_EVERY = 100
"""Operations between two snapshots of a map (``mcsm serve --snapshot-every``)."""
DEFAULT_SNAPSHOTS_KEPT = 5
"""Snapshots kept per map (``--snapshots-kept``): the retract window is the inputs since the
oldest one, between (kept - 1) and kept times ``snapshot_every`` operations."""


@dataclass
class Logged:
    """One applied input of the window: its request, sequence number and current verdict."""

    seq: int
    op: str
    request_id: str
    req: Any
    verdict: wire.Verdict | None = None
    retracted: bool = False


@dataclass
class History:
    snapshot_every: int = DEFAULT_SNAPSHOT_EVERY
    snapshots_kept: int = DEFAULT_SNAPSHOTS_KEPT
    # (seq, map snapshot, deferral state at that seq: None without --gate-defer)
    snapshots: list[tuple[int, dict[str, Any], DeferState | None]] = field(default_factory=list)
    log: list[Logged] = field(default_factory=list)
    by_id: dict[str, Logged] = field(default_factory=dict)

    def start(self, smap: StochasticMap, seq: int, defer: DeferState | None = None) -> None:
        """The first snapshot (the map and its deferral state as they are at ``seq``)."""
        self.snapshots = [(seq, smap.snapshot(), defer)]
        self.log, self.by_id = [], {}

    def record(self, seq: int, op: str, request_id: str, req: Any,
               verdict: wire.Verdict | None, smap: StochasticMap,
               defer: DeferState | None = None) -> None:
        """Log an applied input (after the map changed) and take the scheduled snapshot."""
        entry = Logged(seq, op, request_id, req, verdict)
        self.log.append(entry)
        if ops.get(op).change is not None:  # an input (not a retract): a possible target
            self.by_id[request_id] = entry
        if seq % self.snapshot_every == 0:
            self.snapshots.append((seq, smap.snapshot(), defer))
            self._trim()

    def decided(self, verdicts: dict[str, wire.Verdict]) -> None:
        """Held closures (``--gate-defer``) decided by a later input: their final verdicts."""
        for rid, v in verdicts.items():
            e = self.by_id.get(rid)
            if e is not None:
                e.verdict = v

    def _trim(self) -> None:
        while len(self.snapshots) > max(1, self.snapshots_kept):
            self.snapshots.pop(0)
        oldest = self.snapshots[0][0]
        keep = [e for e in self.log if e.seq > oldest]
        dropped = len(self.log) - len(keep)
        if dropped:
            for e in self.log[:dropped]:
                if self.by_id.get(e.request_id) is e:
                    del self.by_id[e.request_id]
            self.log = keep

    @property
    def window_start(self) -> int:
        """Inputs with a sequence number above this can be retracted or reinstated."""
        return self.snapshots[0][0] if self.snapshots else 0

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
                f"after seq {self.window_start}; see mcsm serve --snapshots-kept)")
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
        seq0, snap, defer0 = base[-1]
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
            if e.seq % self.snapshot_every == 0:
                new_snaps.append((e.seq, smap.snapshot(), None if dfr is None else dfr.state))
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


__all__ = ["History", "Logged", "DEFAULT_SNAPSHOT_EVERY", "DEFAULT_SNAPSHOTS_KEPT"]
