"""Deferred first closures (issue 16 §3, ``mcsm serve --gate-defer [K]``), in the service.

The gate judges a loop closure against the map as it is. After a long stretch on odometry the
map is uncertain, so an early wrong closure can pass and then make the map refuse the true
ones (lock-in, docs/outliers.md). Deferral holds the *first* loop closure of a revisit (no
closure accepted in the last ``revisit_gap`` updates) as ``pending`` until a second closure
agrees with it through the map's joint samples (the cycle test of :func:`cycle_nis`), then
applies both through the gate; if they disagree the held one is rejected and the newer one is
held instead. A held closure whose wait reaches ``expiry`` updates goes through the gate alone
(``on_expiry="gate"``) or is rejected (``"reject"``). The same policy as the client-side
:class:`mcsm_client.outliers.DeferringMap` (which measured it), with one difference of timing
only: expiry is decided at the end of the update that completes the wait rather than at the
start of the next one (the same place in the order, so the same map), so that an update the
core refuses never leaves a held closure half released.

Determinism: :class:`Deferral` is a pure function of its (immutable) :class:`DeferState`, the
map and the update it is given; the held closure is decided inside the processing of a later
update, by the same code in the live server, in replay and in a retraction's re-application
(:mod:`mcsm.map.history`), so all three reproduce every verdict and digest. Its state is part of
the in-memory snapshots (retract) and of the recorded ones (``--restore``).

The cycle test decides the map's state, so it computes like the gate: the cycle's samples,
their NIS against the identity and their spreads all come from the core's kernel (fixed order
of operations, Jacobi eigenvalues; no BLAS or LAPACK), and the threshold from
:func:`mcsm.core.gate.chi2_quantile`: a ``--gate-defer`` recording replays to the same bits on
every CPU.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

from mcsm import wire
from mcsm.core.at import check_samples
from mcsm.core.forest import UpdateResult
from mcsm.core.gate import (
    chart_variance,
    chi2_quantile,
    cycle_samples,
    inverse_samples,
    nis_from_identity,
)
from mcsm.core.smap import DEFAULT_GATE, StochasticMap
from mcsm.errors import McsmError

Array = npt.NDArray[np.float64]

DEFAULT_EXPIRY = 25
"""Updates a held closure waits at most (``--gate-defer`` without K; measured in
docs/outliers.md)."""
DEFAULT_REVISIT_GAP = 25
"""A closure is the first of a revisit when no closure was accepted in this many updates."""
DEFAULT_MAX_LOOSENESS = 4.0
"""A closure is a partner of the held one only when their cycle is this tight (see
:func:`cycle_nis`)."""
PENDING_REASON = "first closure of a revisit: held until a second one agrees"


class Closure(Protocol):
    """An observed AT ``a -> b`` with its samples (a wire update request, a client record)."""

    @property
    def a(self) -> str: ...
    @property
    def b(self) -> str: ...
    @property
    def samples(self) -> Array: ...


def is_loop_closure(smap: StochasticMap, a: str, b: str) -> bool:
    """True when ``a -> b`` would close a loop (both frames known, in one component)."""
    return a in smap and b in smap and smap.root(a) == smap.root(b)


def cycle_nis(smap: StochasticMap, first: Closure, second: Closure) -> tuple[float, int, float]:
    """NIS and dof of the cycle ``X1 ⊕ Q(b1→b2) ⊕ X2⁻¹ ⊕ Q(a2→a1)`` against the identity,
    and how loose the map's part of the cycle is.

    ``Q`` are the map's joint samples (row i of both queries is one draw of the map), ``X1``,
    ``X2`` the two closures' samples; the covariance is the cycle's own sample covariance,
    over its live dimensions (3 planar, 6 in 3-D). ``looseness`` is
    ``(tr C(Q_a) + tr C(Q_b)) / (tr C(X1) + tr C(X2))``: a cycle through a long stretch of
    odometry (two closures to different passes) is loose and tests almost nothing.
    """
    q_b = smap.query(first.b, second.b)
    q_a = smap.query(second.a, first.a)
    cyc = cycle_samples(first.samples, q_b, inverse_samples(second.samples), q_a)
    nis, dof = nis_from_identity(cyc)
    tr_map = chart_variance(q_a) + chart_variance(q_b)
    tr_obs = chart_variance(first.samples) + chart_variance(second.samples)
    return nis, dof, tr_map / max(tr_obs, 1e-300)


@dataclass(frozen=True)
class DeferOptions:
    """The policy's parameters; recorded in the map's config (``gate_defer``)."""

    expiry: int = DEFAULT_EXPIRY
    revisit_gap: int = DEFAULT_REVISIT_GAP
    max_looseness: float = DEFAULT_MAX_LOOSENESS
    on_expiry: str = "gate"

    def __post_init__(self) -> None:
        if not (type(self.expiry) is int and self.expiry >= 1
                and type(self.revisit_gap) is int and self.revisit_gap >= 0):
            raise McsmError("gate_defer: expiry must be an integer >= 1 and revisit_gap >= 0")
        if self.on_expiry not in ("gate", "reject") or not self.max_looseness > 0:
            raise McsmError("gate_defer: on_expiry must be 'gate' or 'reject', "
                            "max_looseness > 0")

    def to_dict(self) -> dict[str, Any]:
        return {"expiry": self.expiry, "revisit_gap": self.revisit_gap,
                "max_looseness": float(self.max_looseness), "on_expiry": self.on_expiry}

    @classmethod
    def from_dict(cls, d: Any) -> DeferOptions | None:
        """The recorded form (None or a dict: no deferral or these options).

        Raises
        ------
        McsmError
            If ``d`` is neither.
        """
        if d is None:
            return None
        if not isinstance(d, dict):
            raise McsmError(f"gate_defer: expected a map or null, got {type(d).__name__}")
        try:
            return cls(int(d["expiry"]), int(d["revisit_gap"]), float(d["max_looseness"]),
                       str(d["on_expiry"]))
        except (KeyError, TypeError, ValueError) as exc:
            raise McsmError(f"gate_defer: unreadable options {d!r}: {exc}") from None


@dataclass(frozen=True)
class Held:
    """The closure waiting for a partner: its request, seq and the update count it came at."""

    request_id: str
    seq: int
    req: Any  # wire.UpdateRequest
    count: int


@dataclass(frozen=True)
class DeferState:
    """Everything the policy remembers (immutable: snapshots share it)."""

    held: Held | None = None
    count: int = 0  # updates seen (left-out ones are not)
    last_closure: int = -(10**9)  # update count of the last accepted closure

    def encode(self) -> dict[str, Any]:
        """As msgpack-able values (the held request as its wire payload)."""
        h = self.held
        held = None if h is None else {
            "id": h.request_id, "seq": h.seq, "count": h.count,
            "request": wire.encode_update(h.req.request_id, h.req.a, h.req.b, h.req.samples,
                                          h.req.sender, trusted=h.req.trusted,
                                          stamp_ns=h.req.stamp_ns)}
        return {"held": held, "count": self.count, "last_closure": self.last_closure}

    @classmethod
    def decode(cls, d: Any, n_samples: int) -> DeferState:
        """Inverse of :meth:`encode`, checked.

        Raises
        ------
        McsmError
            If ``d`` is not an encoded state of a map with ``n_samples`` samples.
        """
        if not isinstance(d, dict):
            raise McsmError("a deferral state is not a map")
        try:
            h = d.get("held")
            held = None if h is None else Held(
                str(h["id"]), int(h["seq"]),
                wire.decode_update(bytes(h["request"]), n_samples), int(h["count"]))
            return cls(held, int(d["count"]), int(d["last_closure"]))
        except (KeyError, TypeError, ValueError) as exc:
            raise McsmError(f"unreadable deferral state: {exc}") from None


@dataclass(frozen=True)
class Outcome:
    """What one update did: its own result (None while it is held) and verdict, and the held
    closure decided meanwhile (request id -> final verdict)."""

    result: UpdateResult | None
    verdict: wire.Verdict
    decided: dict[str, wire.Verdict]


def gated_update(smap: StochasticMap, req: Any, trusted: bool = False
                 ) -> tuple[UpdateResult, wire.Verdict]:
    """``smap.update`` of a wire update request (through the gate unless trusted), with the
    verdict in wire form. Raises what the core raises (the map then unchanged)."""
    r = smap.update(req.a, req.b, req.samples, trusted=req.trusted or trusted)
    v = r.verdict
    return r, wire.Verdict(v.status, v.nis, v.dof, v.threshold, v.reason, req.stamp_ns)


class Deferral:
    """The policy for one map: :meth:`update` applies (or holds) one update request.

    ``state`` may be read and replaced between calls (snapshots, restore); ``quantile`` is the
    cycle test's chi-square quantile (the map's gate, or 0.99 without one).
    """

    def __init__(self, options: DeferOptions, quantile: float | None,
                 state: DeferState | None = None) -> None:
        self.options = options
        self.quantile = DEFAULT_GATE if quantile is None else float(quantile)
        self.state = state if state is not None else DeferState()

    def copy(self, state: DeferState | None = None) -> Deferral:
        return Deferral(self.options, self.quantile, self.state if state is None else state)

    def update(self, smap: StochasticMap, seq: int, req: Any, *, trusted: bool = False
               ) -> Outcome:
        """Apply, hold or pair the update ``req`` (applied as sequence number ``seq``).

        Raises
        ------
        McsmError
            What the core raises for ``req`` when it is applied directly; the map and the
            state are then unchanged. Once the policy has changed the map it raises nothing.
        """
        o = self.options
        st = self.state
        count = st.count + 1
        held = st.held
        decided: dict[str, wire.Verdict] = {}
        if not self._candidate(smap, req) or trusted or req.trusted:
            r, v = gated_update(smap, req, trusted)  # may raise: nothing changed yet
            last = count if r.kind == "loop_closure" else st.last_closure
            self.state = DeferState(held, count, last)
            return Outcome(r, v, self._expire(smap, decided))
        if held is None:
            if count - st.last_closure <= o.revisit_gap:
                r, v = gated_update(smap, req)
                last = count if r.kind == "loop_closure" else st.last_closure
                self.state = DeferState(None, count, last)
                return Outcome(r, v, decided)
            return self._hold(seq, req, count, st.last_closure, decided)
        if not is_loop_closure(smap, held.req.a, held.req.b):
            decided[held.request_id] = _rejected(held.req, "deferred: its frames were removed")
            return self._hold(seq, req, count, st.last_closure, decided)
        nis, dof, loose = cycle_nis(smap, held.req, req)
        if loose > o.max_looseness:  # not a partner: through the gate, the held one waits
            r, v = gated_update(smap, req)
            self.state = DeferState(held, count, st.last_closure)
            return Outcome(r, v, self._expire(smap, decided))
        threshold = chi2_quantile(self.quantile, dof) if dof else float("inf")
        if nis <= threshold:  # they agree: both through the gate, the held one first
            last = st.last_closure
            decided[held.request_id], hr = self._release(smap, held)
            if hr is not None and hr.kind == "loop_closure":
                last = count
            try:
                r, v = gated_update(smap, req)
            except McsmError as exc:  # the map changed already: refuse in the verdict
                self.state = DeferState(None, count, last)
                return Outcome(None, _rejected(req, f"no longer applies: {type(exc).__name__}"),
                               decided)
            if r.kind == "loop_closure":
                last = count
            self.state = DeferState(None, count, last)
            return Outcome(r, v, decided)
        decided[held.request_id] = _rejected(
            held.req, f"deferred: the cycle with request {req.request_id} failed "
                      f"(NIS {nis:.3g} > {threshold:.3g}, dof {dof})", nis, dof, threshold)
        return self._hold(seq, req, count, st.last_closure, decided)

    @staticmethod
    def _candidate(smap: StochasticMap, req: Any) -> bool:
        """A valid full-frame loop closure between two full frames: anything else (a point, a
        mixed or a malformed one) goes straight to the core, which applies it or refuses it,
        so a request the core would refuse is never held."""
        if not (req.a != req.b and getattr(req.samples, "ndim", 0) == 2
                and req.samples.shape[-1] == 7 and is_loop_closure(smap, req.a, req.b)
                and not smap.is_point(req.a) and not smap.is_point(req.b)):
            return False
        try:
            check_samples(req.samples, smap.n_samples, 7)
        except McsmError:
            return False
        return True

    def _hold(self, seq: int, req: Any, count: int, last: int,
              decided: dict[str, wire.Verdict]) -> Outcome:
        self.state = DeferState(Held(req.request_id, seq, req, count), count, last)
        v = wire.Verdict("pending", None, 0, None,
                         f"{PENDING_REASON} (at most {self.options.expiry} updates)",
                         req.stamp_ns)
        return Outcome(None, v, decided)

    def _release(self, smap: StochasticMap, held: Held
                 ) -> tuple[wire.Verdict, UpdateResult | None]:
        """Apply the held closure through the gate; a closure the core now refuses (its frames
        changed) is rejected in its verdict."""
        if not is_loop_closure(smap, held.req.a, held.req.b):
            return _rejected(held.req, "deferred: its frames were removed"), None
        try:
            r, v = gated_update(smap, held.req)
        except McsmError as exc:
            return _rejected(held.req, f"no longer applies: {type(exc).__name__}"), None
        return v, r

    def _expire(self, smap: StochasticMap, decided: dict[str, wire.Verdict]
                ) -> dict[str, wire.Verdict]:
        """At the end of an update: release a held closure whose wait is over."""
        st = self.state
        h = st.held
        if h is None or st.count - h.count < self.options.expiry:
            return decided
        if self.options.on_expiry == "reject":
            decided[h.request_id] = _rejected(h.req, "deferred: expired without an agreeing "
                                                     "closure")
            self.state = replace(st, held=None)
            return decided
        decided[h.request_id], r = self._release(smap, h)
        last = st.count if r is not None and r.kind == "loop_closure" else st.last_closure
        self.state = DeferState(None, st.count, last)
        return decided

    def pending_id(self) -> str | None:
        return None if self.state.held is None else self.state.held.request_id


def _rejected(req: Any, reason: str, nis: float | None = None, dof: int = 0,
              threshold: float | None = None) -> wire.Verdict:
    return wire.Verdict("rejected", nis, dof, threshold, reason, req.stamp_ns)


__all__ = ["DeferOptions", "DeferState", "Deferral", "Held", "Outcome", "cycle_nis",
           "gated_update", "is_loop_closure", "DEFAULT_EXPIRY"]
