"""Wrong loop closures, on the client side (issue 16 §3, §5): deferral and exact retraction.

Two policies over a :class:`mcsm.StochasticMap`, pure numpy plus :mod:`mcsm.core`:

* :class:`Ledger` keeps every input that reached the map (accepted or rejected by its gate),
  in the order the map saw them, with a snapshot every ``snapshot_every`` inputs. Retracting an
  input (or reinstating a rejected one as trusted) restores the last snapshot before it and
  re-applies every later input without it (or with it): the result has the digest of a map
  that never had it (or always had it), because the core's replay is deterministic. The later
  inputs go through the gate again, so their verdicts may change (a true closure that a wrong
  one had pushed out can come back).
* :class:`DeferringMap` holds the first loop closure of a revisit as ``pending`` until a second
  closure agrees with it through the map's joint samples (the cycle test
  ``X1 ⊕ Q(b1→b2) ⊕ X2⁻¹ ⊕ Q(a2→a1) ≈ I`` at the gate's quantile,
  :func:`mcsm.map.deferral.cycle_nis`), then applies both through the gate; one that disagrees
  is rejected and the newer closure waits instead. A pending closure expires after ``expiry``
  inputs: it then goes through the gate alone (``on_expiry="gate"``) or is rejected
  (``"reject"``). This answers the gate's lock-in: an early wrong closure that passes because
  the map is still uncertain, and then makes the map reject the true ones. The server runs
  the same policy (``mcsm serve --gate-defer``, :mod:`mcsm.map.deferral`).

Statuses: ``accepted``, ``rejected`` (by the gate or the cycle test), ``pending``,
``retracted``, ``reinstated`` (issue 16 §2).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt
from mcsm.core import StochasticMap, Verdict
from mcsm.core.gate import chi2_quantile
from mcsm.map.deferral import cycle_nis, is_loop_closure  # the server's --gate-defer uses them too

Array = npt.NDArray[np.float64]


@dataclass(frozen=True)
class Record:
    """One input as the map saw it: an update ``a → b`` with its samples."""

    request_id: int
    a: str
    b: str
    samples: Array = field(repr=False)
    trusted: bool = False


@dataclass(frozen=True)
class Outcome:
    """The current verdict of one input (``status`` as in issue 16 §2)."""

    request_id: int
    status: str
    verdict: Verdict
    kind: str = ""


# ------------------------------------------------------------------------------------ ledger
class Ledger:
    """A map with its applied inputs, snapshots and exact retract/reinstate by replay.

    Parameters
    ----------
    smap : the map to drive (fresh, or at the state the ledger starts from)
    snapshot_every : a snapshot before every ``snapshot_every``-th input (memory: one copy of
        the map each, 11 MB at M = 1000, N = 200)
    """

    def __init__(self, smap: StochasticMap, *, snapshot_every: int = 100) -> None:
        if snapshot_every < 1:
            raise ValueError("snapshot_every must be >= 1")
        self.map = smap
        self.snapshot_every = snapshot_every
        self.records: list[Record] = []
        self.excluded: set[int] = set()  # retracted request ids
        self.forced: set[int] = set()  # reinstated request ids (applied as trusted)
        self.outcomes: dict[int, Outcome] = {}
        self._position: dict[int, int] = {}
        self._snapshots: dict[int, dict[str, object]] = {0: smap.snapshot()}
        self.replayed_inputs = 0  # inputs re-applied by retract/reinstate so far

    def apply(self, record: Record) -> Outcome:
        """Apply a new input at the end and record it (with its verdict)."""
        if record.request_id in self._position:
            raise ValueError(f"request {record.request_id} is already recorded")
        k = len(self.records)
        if k % self.snapshot_every == 0 and k not in self._snapshots:
            self._snapshots[k] = self.map.snapshot()
        self.records.append(record)
        self._position[record.request_id] = k
        return self._apply_one(record)

    def _apply_one(self, record: Record) -> Outcome:
        rid = record.request_id
        if rid in self.excluded:
            prev = self.outcomes.get(rid)
            out = Outcome(rid, "retracted", prev.verdict if prev else Verdict("retracted"))
        else:
            trusted = record.trusted or rid in self.forced
            r = self.map.update(record.a, record.b, record.samples, trusted=trusted)
            status = r.verdict.status
            if rid in self.forced:
                status = "reinstated"
            out = Outcome(rid, status, r.verdict, r.kind)
        self.outcomes[rid] = out
        return out

    def status(self, request_id: int) -> str:
        return self.outcomes[request_id].status

    def retract(self, request_ids: Iterable[int]) -> list[Outcome]:
        """Take inputs back; returns the outcomes that changed (the later inputs' too)."""
        ids = [i for i in request_ids if i not in self.excluded]
        self.excluded.update(ids)
        self.forced.difference_update(ids)
        return self._replay_from(ids)

    def reinstate(self, request_ids: Iterable[int]) -> list[Outcome]:
        """Put inputs back (retracted or rejected), applied as trusted where they were."""
        ids = [i for i in request_ids if i not in self.forced]
        self.excluded.difference_update(ids)
        self.forced.update(ids)
        return self._replay_from(ids)

    def _replay_from(self, ids: Sequence[int]) -> list[Outcome]:
        if not ids:
            return []
        start = min(self._position[i] for i in ids)
        base = max(k for k in self._snapshots if k <= start)
        for k in [k for k in self._snapshots if k > base]:
            del self._snapshots[k]
        self.map = StochasticMap.from_snapshot(self._snapshots[base], threads=self.map.threads)
        before = dict(self.outcomes)
        for k in range(base, len(self.records)):
            if k % self.snapshot_every == 0 and k not in self._snapshots:
                self._snapshots[k] = self.map.snapshot()
            self._apply_one(self.records[k])
            self.replayed_inputs += 1
        return [o for rid, o in self.outcomes.items()
                if before.get(rid) is None or before[rid].status != o.status]


# --------------------------------------------------------------------------------- deferral
class DeferringMap:
    """Gate plus deferral of the first loop closure of a revisit, over a :class:`Ledger`.

    Parameters
    ----------
    ledger : the map (with its gate) and its record
    revisit_gap : a loop closure is the first of a revisit when no closure was accepted in the
        last ``revisit_gap`` inputs
    expiry : inputs after which a pending closure is released (``on_expiry``)
    gate : chi-square quantile of the cycle test (default: the map's gate, or 0.99)
    on_expiry : ``"gate"`` (apply it alone, through the map's gate) or ``"reject"``
    max_looseness : a closure is a partner of the held one only when the map's part of their
        cycle is tight (:func:`cycle_nis` looseness at most this); any other closure goes
        through the gate as usual while the held one keeps waiting (and, released later, meets
        the gate of a map those closures have corrected)
    """

    def __init__(self, ledger: Ledger, *, revisit_gap: int = 25, expiry: int = 25,
                 gate: float | None = None, on_expiry: str = "gate",
                 max_looseness: float = 4.0) -> None:
        if on_expiry not in ("gate", "reject"):
            raise ValueError("on_expiry must be 'gate' or 'reject'")
        self.ledger = ledger
        self.revisit_gap = revisit_gap
        self.expiry = expiry
        self.gate = gate if gate is not None else (ledger.map.gate or 0.99)
        self.on_expiry = on_expiry
        self.max_looseness = max_looseness
        self.pending: tuple[Record, int] | None = None  # the held closure and its input count
        self.outcomes: dict[int, Outcome] = {}
        self._inputs = 0
        self._last_closure = -(10**9)  # input count of the last accepted closure

    @property
    def map(self) -> StochasticMap:
        return self.ledger.map

    def update(self, record: Record) -> list[Outcome]:
        """Submit one input; returns every outcome decided now (``pending`` included)."""
        self._inputs += 1
        out: list[Outcome] = []
        if self.pending is not None and self._inputs - self.pending[1] > self.expiry:
            out += self._expire()
        smap = self.map
        point = record.samples.shape[-1] == 3
        if record.trusted or point or not is_loop_closure(smap, record.a, record.b):
            return out + [self._apply(record)]
        if self.pending is None:
            if self._inputs - self._last_closure <= self.revisit_gap:
                return out + [self._apply(record)]
            return out + [self._hold(record)]
        held = self.pending[0]
        if held.a not in smap or held.b not in smap:
            self.pending = None
            out.append(self._reject(held, "deferred: its frames were removed"))
            return out + [self._hold(record)]
        nis, dof, loose = cycle_nis(smap, held, record)
        if loose > self.max_looseness:
            return out + [self._apply(record, counts=False)]
        threshold = chi2_quantile(self.gate, dof) if dof else float("inf")
        if nis <= threshold:
            self.pending = None
            return out + [self._apply(held), self._apply(record)]
        self.pending = None
        out.append(self._reject(held, f"deferred: cycle with request {record.request_id} "
                                      f"failed (NIS {nis:.3g} > {threshold:.3g}, dof {dof})"))
        return out + [self._hold(record)]

    def flush(self) -> list[Outcome]:
        """Release a pending closure now (end of a run), by the expiry rule."""
        return self._expire() if self.pending is not None else []

    def _expire(self) -> list[Outcome]:
        assert self.pending is not None
        held = self.pending[0]
        self.pending = None
        if self.on_expiry == "reject" or held.a not in self.map or held.b not in self.map:
            return [self._reject(held, "deferred: expired without an agreeing closure")]
        return [self._apply(held)]

    def _hold(self, record: Record) -> Outcome:
        self.pending = (record, self._inputs)
        o = Outcome(record.request_id, "pending",
                    Verdict("pending", reason="first closure of a revisit: waiting for a "
                                              "second one to agree"))
        self.outcomes[record.request_id] = o
        return o

    def _reject(self, record: Record, reason: str) -> Outcome:
        o = Outcome(record.request_id, "rejected", Verdict("rejected", reason=reason))
        self.outcomes[record.request_id] = o
        return o

    def _apply(self, record: Record, counts: bool = True) -> Outcome:
        o = self.ledger.apply(record)
        if o.kind == "loop_closure" and counts:
            self._last_closure = self._inputs
        self.outcomes[record.request_id] = o
        return o

    def final_status(self, request_id: int) -> str:
        """The status now: the ledger's for applied inputs (it follows retractions)."""
        if request_id in self.ledger.outcomes:
            return self.ledger.outcomes[request_id].status
        return self.outcomes[request_id].status


__all__ = ["DeferringMap", "Ledger", "Outcome", "Record", "cycle_nis", "is_loop_closure"]
