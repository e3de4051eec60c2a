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
    snapshots: list[tuple[int, dict[str, Any]]] = field(default_factory=list)
    log: list[Logged] = field(default_factory=list)
    by_id: dict[str, Logged] = field(default_factory=dict)

    def start(self, smap: StochasticMap, seq: int) -> None:
        """The first snapshot (the map as it is at ``seq``)."""
        self.snapshots = [(seq, smap.snapshot())]
        self.log, self.by_id = [], {}

    def record(self, seq: int, op: str, request_id: str, req: Any,
               verdict: wire.Verdict | None, smap: StochasticMap) -> None:
        """Log an applied input (after the map changed) and take the scheduled snapshot."""
        entry = Logged(seq, op, request_id, req, verdict)
        self.log.append(entry)
        if ops.get(op).change is not None:  # an input (not a retract): a possible target
            self.by_id[request_id] = entry
        if seq % self.snapshot_every == 0:
            self.snapshots.append((seq, smap.snapshot()))
            self._trim()

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
        if retract and e.retracted:
            raise InvalidOperation(f"request {request_id!r} is already retracted")
        rejected = e.verdict is not None and e.verdict.status == "rejected"
        if not retract and not (e.retracted or rejected):
            raise InvalidOperation(f"request {request_id!r} is neither retracted nor rejected")
        return e

    def rebuild(self, target: Logged, retract: bool, threads: int | None
                ) -> tuple[StochasticMap, dict[str, wire.Verdict], Callable[[], None]]:
        """The map with ``target`` left out (``retract``) or put back, from the last snapshot
        before it plus every later input of the window; the verdicts that changed; and a
        function that commits the new window (snapshots, flags, verdicts) once the caller
        has swapped the map in. Raises nothing that leaves a half-changed window."""
        base = [s for s in self.snapshots if s[0] < target.seq]
        seq0, snap = base[-1]
        smap = StochasticMap.from_snapshot(snap, threads=threads)
        new_snaps = list(base)
        changed: dict[str, wire.Verdict] = {}
        new_state: dict[int, tuple[bool, wire.Verdict | None]] = {}
        for e in self.log:
            if e.seq <= seq0:
                continue
            left_out = (e.retracted and e is not target) or (e is target and retract)
            verdict = e.verdict
            op = ops.get(e.op)
            if op.change is not None:
                if left_out:
                    verdict = _with_status(verdict, "retracted")
                else:
                    try:  # a reinstated update goes back in whatever the gate says
                        verdict = op.change(smap, e.req, trusted=e is target).verdict
                    except McsmError as exc:  # it no longer applies (its frame is gone)
                        verdict = wire.Verdict("rejected", None, 0, None,
                                               f"no longer applies: {type(exc).__name__}")
                    if e is target:
                        verdict = _with_status(verdict, "reinstated")
                if verdict != e.verdict and op.retractable:
                    changed[e.request_id] = verdict  # type: ignore[assignment]
            new_state[e.seq] = (left_out if op.retractable else e.retracted, verdict)
            if e.seq % self.snapshot_every == 0:
                new_snaps.append((e.seq, smap.snapshot()))

        def commit() -> None:
            for e in self.log:
                if e.seq in new_state:
                    e.retracted, e.verdict = new_state[e.seq]
            self.snapshots = new_snaps
            self._trim()

        return smap, changed, commit


def _with_status(v: wire.Verdict | None, status: str) -> wire.Verdict:
    return wire.Verdict(status) if v is None else replace(v, status=status)


__all__ = ["History", "Logged", "DEFAULT_SNAPSHOT_EVERY", "DEFAULT_SNAPSHOTS_KEPT"]
