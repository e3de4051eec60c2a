"""The Monte Carlo stochastic map (PAPER §3): the public facade of the core.

:class:`StochasticMap` keeps the map's options and dispatches an update to the forest's
structure (new frame, new component, join: :mod:`mcsm.core.forest`) or, for a loop closure
(case II), to the joint update (:mod:`mcsm.core.joint`, the default, compiled and portable)
or the paper's own update (:mod:`mcsm.core.paper`, machine-bound, kept for reproduction).
A loop closure can be gated first: its normalised innovation against the map's prediction is
compared with a chi-square quantile (:mod:`mcsm.core.gate`); a rejected one leaves the map
unchanged and says so in :attr:`UpdateResult.verdict`. The map keeps a record of every
constraint it applied (:mod:`mcsm.core.factors`), from which it can relinearise: solve for the
maximum a posteriori estimate of a component and redraw its samples
(:mod:`mcsm.core.relinearize`), on request or by its :class:`Policy`.

Every refused call raises an :class:`mcsm.errors.McsmError` and leaves the map bit-identical.
"""

from __future__ import annotations

import json
from dataclasses import replace
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from mcsm.core import joint, relin
from mcsm.core.at import check_samples
from mcsm.core.device import backend_for
from mcsm.core.factors import FactorHistory, Group
from mcsm.core.forest import (
    Forest,
    RemoveResult,
    Submap,
    UpdateResult,
    Verdict,
    check_frame_name,
)
from mcsm.core.gate import chi2_quantile, lower_quantile, median
from mcsm.core.marginalise import marginalise
from mcsm.core.paper import paper_update, paper_update_tangent
from mcsm.core.recentre import recentre, recentring
from mcsm.core.relinearize import (
    CALIBRATE_QUANTILE,
    DEFAULT_HISTORY_BYTES,
    REGATE_WINDOW,
    Policy,
    RelinReport,
    calibrating,
    relinearize,
    why_not,
)
from mcsm.core.storage import Component, to_rows
from mcsm.errors import InvalidOperation, InvalidSamples

Array = npt.NDArray[np.float64]
Method = Literal["joint", "paper"]

METHODS = ("joint", "paper")
SPACES = ("tangent", "quaternion")
GAINS = ("direct", "endpoints")
RULES = ("ensrf", "denkf", "enkf")
default_threads = joint.default_threads
DEFAULT_GATE = 0.99
"""The loop-closure gate's default chi-square quantile (measured in docs/outliers.md)."""
DEFAULT_GATE_SCALE: dict[str, Any] = {"window": 15, "open": 3.0, "max": 30.0}
"""The gate's default scale rule: the threshold is multiplied by ``m / open`` clipped to
[1, ``max``], where ``m`` is the median, over the last ``window`` gated closures, of their NIS
over the chi-square median for their dof (measured in docs/design.md, "Relinearisation")."""
DEFAULT_POLICY: Policy | None = Policy(nis=0.95, regate=1, gap=25, spread=1.3, recentre=True,
                                       readmit=300, calibrate=15)
"""The default automatic relinearisation: after an accepted loop closure with NIS above the
0.95 quantile and at every gate failure (then gated again), at most once per 25 inputs of a
component, drawing 1.3 x the posterior's deviations; after every other accepted closure a
re-centring (the component solved, its samples' means moved to the solution) that also admits
the closures refused within the last 300 inputs that the solution agrees with; the gate scaled
by the last 15 of those (docs/relinearisation.md). The defaults before: without
``calibrate``; then without ``recentre``, ``readmit``; first ``REPAIR_ONLY``."""


class StochasticMap(Forest):
    """A forest of star graphs of ATs with N samples each (PAPER §3).

    Parameters
    ----------
    n_samples : N, constant for the whole map
    method : ``"joint"`` (default) or ``"paper"`` (PAPER Fig. 3, kept for reproduction;
        machine-bound numpy in the quaternion space)
    space : ``"tangent"`` (default, the ⊞ chart of PAPER §5) or ``"quaternion"`` (the paper's
        7-D Euclidean treatment), the vector space of every linear step
    analysis : rule of the joint update: ``"ensrf"`` (default; deterministic square root),
        ``"denkf"`` or ``"enkf"`` (perturbed observations); see :mod:`mcsm.core.analysis`
    shrink : correlation-shrink constant c (Anderson 2012) for the cross-covariances of the
        joint update (default 4; None turns it off)
    inflation : multiplicative inflation of every edge's anomalies after each loop closure
        (a number in [1, 2)), or ``"adaptive"`` (driven by a running average of the loop
        closures' NIS per dof)
    gain : ``"direct"`` (default) or ``"endpoints"`` (tangent space only), the estimator of
        every edge's cross-covariance with the predicted observation (:mod:`mcsm.core.joint`)
    gate : chi-square quantile in (0, 1) of the loop-closure gate (default
        :data:`DEFAULT_GATE`, 0.99), or None for no gate: a loop closure whose NIS exceeds the
        quantile for its dof is rejected (docs/outliers.md: why 0.99)
    history : bound in bytes of the factor history (default
        :data:`~mcsm.core.relinearize.DEFAULT_HISTORY_BYTES`; beyond it the oldest removed
        frames are marginalised into a dense prior), or None: no history, no relinearisation
    relinearize : the automatic relinearisation :class:`Policy` (default
        :data:`DEFAULT_POLICY`), a dict of its fields, or None (only on request,
        :meth:`relinearize`)
    threads : threads for the joint update's frame pass (default :func:`default_threads`).
        Not part of :meth:`options` or the state: every thread count gives the same bits.
    device : ``"cpu"`` (default), ``"cuda"`` / ``"cuda:K"`` (the edges in GPU memory, the
        passes that grow with the map run there: :mod:`mcsm.core.device`; needs the ``gpu``
        extra, CuPy), or a :class:`mcsm.core.device.Backend` (the tests' emulated one). Not
        part of :meth:`options` or the state: a map on a GPU has the same digests as on a CPU.
        ``method="paper"`` runs on the CPU only.
    """

    def __init__(
        self,
        n_samples: int,
        *,
        method: str = "joint",
        space: str = "tangent",
        analysis: str = "ensrf",
        shrink: float | None = 4.0,
        inflation: float | str = 1.0,
        gain: str = "direct",
        gate: float | None = DEFAULT_GATE,
        gate_scale: dict[str, Any] | None = DEFAULT_GATE_SCALE,
        history: int | None = DEFAULT_HISTORY_BYTES,
        relinearize: Policy | dict[str, Any] | None = DEFAULT_POLICY,
        threads: int | None = None,
        device: object = "cpu",
    ) -> None:
        if not isinstance(n_samples, int) or isinstance(n_samples, bool) or n_samples < 2:
            raise InvalidOperation(f"n_samples must be an integer >= 2, got {n_samples!r}")
        if method not in METHODS:
            raise InvalidOperation(f"method must be one of {METHODS}, got {method!r}")
        if space not in SPACES:
            raise InvalidOperation(f"space must be one of {SPACES}, got {space!r}")
        if analysis not in RULES:
            raise InvalidOperation(f"analysis must be one of {RULES}, got {analysis!r}")
        if shrink is not None and not (isinstance(shrink, (int, float))
                                       and np.isfinite(shrink) and shrink >= 0):
            raise InvalidOperation(f"shrink must be None or >= 0, got {shrink!r}")
        if inflation != "adaptive" and not (
                isinstance(inflation, (int, float)) and np.isfinite(inflation)
                and 1.0 <= inflation < 2.0):
            raise InvalidOperation(f"inflation must be in [1, 2) or 'adaptive', got {inflation!r}")
        if gain not in GAINS:
            raise InvalidOperation(f"gain must be one of {GAINS}, got {gain!r}")
        if gain == "endpoints" and space != "tangent":
            raise InvalidOperation("gain='endpoints' works in the tangent space only")
        if gate is not None and not (isinstance(gate, (int, float)) and not isinstance(gate, bool)
                                     and 0.0 < gate < 1.0):
            raise InvalidOperation(f"gate must be None or a quantile in (0, 1), got {gate!r}")
        if gate_scale is not None and not (
                isinstance(gate_scale, dict) and set(gate_scale) == {"window", "open", "max"}
                and isinstance(gate_scale["window"], int) and 1 <= gate_scale["window"] <= 999
                and all(isinstance(gate_scale[k], (int, float)) and 1.0 <= gate_scale[k]
                        for k in ("open", "max"))):
            raise InvalidOperation(f"gate_scale must be None or {{'window': K, 'open': T, "
                                   f"'max': S}} (K in [1, 999], T, S >= 1), got {gate_scale!r}")
        if history is not None and not (isinstance(history, int) and not isinstance(history, bool)
                                        and 2**16 <= history <= 2**40):
            raise InvalidOperation(f"history must be None or a byte count in [2**16, 2**40], "
                                   f"got {history!r}")
        policy = Policy.from_plain(relinearize) if isinstance(relinearize, dict) else relinearize
        if policy is not None and not isinstance(policy, Policy):
            raise InvalidOperation(f"relinearize must be None, a Policy or a dict, "
                                   f"got {relinearize!r}")
        if policy is not None and history is None:
            if relinearize is not DEFAULT_POLICY:
                raise InvalidOperation("automatic relinearisation needs a history "
                                       "(history=None)")
            policy = None  # history=None alone turns the default policy off
        if threads is not None and (not isinstance(threads, int) or isinstance(threads, bool)
                                    or not 1 <= threads <= 64):
            raise InvalidOperation(f"threads must be None or an integer in [1, 64], "
                                   f"got {threads!r}")
        if device != "cpu" and method == "paper":
            raise InvalidOperation("method='paper' runs on the CPU only: use device='cpu'")
        super().__init__(n_samples, backend_for(device))
        self.method: Method = method  # type: ignore[assignment]
        self.space = space
        self.analysis = analysis
        self.shrink = None if shrink is None else float(shrink)
        self.inflation: float | str = inflation if inflation == "adaptive" else float(inflation)
        self.gain = gain
        self.gate = None if gate is None else float(gate)
        self._nis_avg = 1.0  # running NIS average of adaptive inflation (part of the state)
        self.gate_scale = None if gate_scale is None or gate is None else {
            "window": int(gate_scale["window"]), "open": float(gate_scale["open"]),
            "max": float(gate_scale["max"])}
        self._gate_u: list[float] = []  # the gate's recent NIS / median NIS (part of the state)
        self._gate_fail: list[int] = []  # the last gated closures' failures (policy regate)
        self.threads = default_threads() if threads is None else threads
        self._spare: Array | None = None  # the buffer the last joint update replaced
        self.factor_history = None if history is None else FactorHistory(history)
        self.policy: Policy | None = policy
        self._track_fail = policy is not None and policy.regate is not None

    # ------------------------------------------------------------------ introspection
    @property
    def device(self) -> str:
        """Where the map's edges live: ``cpu``, ``cuda:K`` or a test backend's name."""
        return "cpu" if self.backend is None else self.backend.name

    def memory(self) -> dict[str, Any]:
        """The memory the map holds where its edges live: ``device`` (as :attr:`device`),
        ``bytes`` (every component's edges and flags plus the loop closure's spare buffer)
        and, on a GPU, ``free`` (bytes the device has free now)."""
        spare = 0 if self._spare is None else int(self._spare.nbytes)
        out: dict[str, Any] = {"device": self.device, "bytes": self.storage_bytes() + spare}
        if self.backend is not None:
            out["free"] = int(self.backend.free_bytes())
        return out

    @property
    def nis_avg(self) -> float:
        """The running NIS average per dof that adaptive inflation steers by (1 at start)."""
        return self._nis_avg

    @property
    def portable(self) -> bool:
        """True when every update of this map gives the same bits on every CPU (all but
        ``method="paper"`` in the quaternion space, whose loop closure runs on numpy/BLAS)."""
        return not (self.method == "paper" and self.space == "quaternion")

    def options(self) -> dict[str, Any]:
        """The constructor arguments, as a plain dict (round-trips through from_options).
        ``gate``, ``history`` and ``relinearize`` are left out when they are None, so a map
        without them has the options (and digest) it had before they existed."""
        o: dict[str, Any] = {"n_samples": self.n_samples, "method": self.method,
                             "space": self.space, "analysis": self.analysis,
                             "shrink": self.shrink, "inflation": self.inflation,
                             "gain": self.gain}
        if self.gate is not None:
            o["gate"] = self.gate
        if self.gate_scale is not None:
            o["gate_scale"] = dict(self.gate_scale)
        if self.factor_history is not None:
            o["history"] = self.factor_history.bound_bytes
        if self.policy is not None:
            o["relinearize"] = self.policy.to_plain()
        return o

    @classmethod
    def from_options(cls, options: dict[str, Any], device: object = "cpu") -> StochasticMap:
        """Build an empty map from :meth:`options` output (as recorded). A missing ``gate``
        means no gate, a missing ``history`` or ``relinearize`` none: the options of a map
        recorded before they existed, or of one without them (:meth:`options` leaves them
        out), rebuild that map."""
        o = dict(options)
        n = o.pop("n_samples")
        o.setdefault("gate", None)
        o.setdefault("gate_scale", None)
        o.setdefault("history", None)
        o.setdefault("relinearize", None)
        return cls(int(n), **o, device=device)

    def _digest_header(self, h: Any) -> None:
        h.update(json.dumps(self.options(), sort_keys=True).encode())
        if self.inflation == "adaptive":
            h.update(np.float64(self._nis_avg).tobytes())
        if self.gate_scale is not None:
            h.update(np.array(self._gate_u, dtype="<f8").tobytes())
        if self._track_fail:
            h.update(bytes(self._gate_fail))
        if self.factor_history is not None:
            self.factor_history.digest_update(h, calibrated=calibrating(self.policy))

    def snapshot(self) -> dict[str, Any]:
        """The whole state (options, structure, edges, adaptive-inflation average, factor
        history) as plain values and arrays; :meth:`from_snapshot` rebuilds a map with the same
        digest."""
        snap = {"options": self.options(), "nis_avg": self._nis_avg, **super().snapshot()}
        if self.gate_scale is not None:
            snap["gate_u"] = list(self._gate_u)
        if self._track_fail:
            snap["gate_fail"] = list(self._gate_fail)
        if self.factor_history is not None:
            snap["factor_history"] = self.factor_history.to_plain()
        return snap

    @classmethod
    def from_snapshot(cls, snap: dict[str, Any], threads: int | None = None,
                      device: object = "cpu") -> StochasticMap:
        m = cls.from_options({**dict(snap["options"]), "threads": threads}, device=device)
        m.restore_snapshot(snap)
        m._nis_avg = float(snap["nis_avg"])
        m._gate_u = [float(u) for u in snap.get("gate_u", [])]
        m._gate_fail = [int(u) for u in snap.get("gate_fail", [])]
        if m.factor_history is not None:
            m.factor_history = FactorHistory.from_plain(snap["factor_history"])
        return m

    # ------------------------------------------------------------------ updates
    def update(self, a: str, b: str, samples: Array, *, trusted: bool = False) -> UpdateResult:
        """Apply the observation ``samples`` of b seen from a.

        ``samples`` ``(N, 7)``: an AT a→b. ``(N, 3)``: the position of point frame b in a.
        New frames are added, two components are joined (case I) or a loop is closed
        (case II). A gated loop closure that fails the gate is not applied
        (``result.kind == "rejected"``, ``result.verdict.status == "rejected"``) unless
        ``trusted``. Raises an McsmError and changes nothing on failure.
        """
        check_frame_name(a)
        check_frame_name(b)
        if a == b:
            raise InvalidOperation(f"an update needs two different frames, got {a!r} twice")
        if not isinstance(samples, np.ndarray):
            raise InvalidSamples(f"expected a numpy array, got {type(samples).__name__}")
        width = samples.shape[-1] if samples.ndim == 2 else -1
        if width not in (3, 7):
            raise InvalidSamples(f"expected shape (N, 7) or (N, 3), got {samples.shape}")
        x = check_samples(samples, self.n_samples, width)
        point = width == 3
        has_a, has_b = a in self._where, b in self._where
        if has_a and self.is_point(a):
            raise InvalidOperation(f"{a!r} is a point frame: it has no orientation to observe from")
        if has_b and not point and self.is_point(b):
            raise InvalidOperation(f"{b!r} is a point frame: observe it with (N, 3) samples")
        if has_b and point and not self.is_point(b):
            raise InvalidOperation(f"{b!r} is a full frame: observe it with (N, 7) samples")
        x_rows = to_rows(x)
        h = self.factor_history
        # the input's moments first: a refusal here leaves the map unchanged
        zw = relin.moments(x_rows, point) if h is not None else None
        join: tuple[int, int, str] | None = None

        if not has_a and not has_b:
            r = self._new_component(a, b, x_rows, point)
        elif has_a and not has_b:
            r = self._add_leaf(a, b, x_rows, point, inverse=False)
        elif not has_a:
            if point:
                raise InvalidOperation(
                    f"a point observation cannot place the unknown observer {a!r}")
            r = self._add_leaf(b, a, x_rows, point, inverse=True)
        elif self._where[a] != self._where[b]:
            join = (self._where[a], self._where[b], self.root(b))
            r = self._join(a, b, x_rows, point)
        else:
            r = self._loop_closure(a, b, x, x_rows, point, trusted)
        if h is None or zw is None:
            return r
        cid = self._where[a]
        if r.kind == "rejected":
            self._keep_refused(h, cid, a, b, point, zw, r.relin is not None, r.verdict)
            return r
        self._record(h, cid, a, b, point, r.kind, r.verdict, zw, join)
        report = r.relin if r.relin is not None else self._automatic(h, cid, r)
        if h.over_bound():
            marginalise(self)
        return r if report is r.relin else replace(r, relin=report)

    # ------------------------------------------------------------------ history
    def _means_world(self, cid: int, frames: list[str]) -> Array:
        """Mean poses of ``frames`` of component ``cid`` in its group's world frame."""
        h = self.factor_history
        assert h is not None
        return relin.transform(h.groups[cid].world, self._edge_means(cid, frames),
                               np.array([self.is_point(f) for f in frames], dtype=np.int32))

    def _edge_means(self, cid: int, frames: list[str]) -> Array:
        """Mean poses (root frame) of ``frames`` of component ``cid``, from host copies."""
        c = self._comps[cid]
        rows = np.stack([np.asarray(c.edge_rows(c.index[f]), dtype=np.float64)
                         for f in frames])
        flags = np.array([c.is_point(c.index[f]) for f in frames], dtype=np.uint8)
        return relin.means(rows, np.arange(len(frames), dtype=np.int64), flags)

    def _record(self, h: FactorHistory, cid: int, a: str, b: str, point: bool, kind: str,
                verdict: Verdict, zw: tuple[Array, Array], join: tuple[int, int, str] | None
                ) -> None:
        """Put an applied input into the history (new variables, merged groups, the factor)."""
        if kind == "new_component":
            h.groups[cid] = Group()
        if join is not None:
            self._record_join(h, *join)
        g = h.groups.get(cid)
        if g is None or g.tainted:
            return
        for f in (a, b):
            if f not in h.var_of:
                h.new_var(f, self.is_point(f), cid, self._means_world(cid, [f])[0])
        # a closure the gate passed (or would have: a trusted one within the threshold is
        # recorded as if it had gone through it); a trusted one beyond it is never trimmed
        gated = kind == "loop_closure" and verdict.threshold is not None \
            and verdict.nis is not None and verdict.nis <= verdict.threshold
        h.add_factor(point, h.var_of[a], h.var_of[b], *zw, robust=gated)
        g.since += 1

    def _keep_refused(self, h: FactorHistory, cid: int, a: str, b: str, point: bool,
                      zw: tuple[Array, Array], burst: bool, verdict: Verdict | None) -> None:
        """A closure the gate refused: kept for re-admission (``Policy.readmit``), marked if
        its component was just relinearised because of refusals (``regate``)."""
        p = self.policy
        if p is None or p.readmit is None:
            return
        h.age_pending(p.readmit)
        g = h.groups.get(cid)
        if g is None or g.tainted or a not in h.var_of or b not in h.var_of:
            return
        v, u = verdict, 0.0
        if self.gate is not None and v is not None and v.dof and v.nis:
            u = float(v.nis) / chi2_quantile(self.gate, v.dof)  # its ratio, for calibrate
        h.add_pending(point, h.var_of[a], h.var_of[b], *zw, u=u)
        if burst:  # the regate relinearisation ran for this closure
            h.pending["burst"][-1] = 1

    def _record_join(self, h: FactorHistory, cid1: int, cid2: int, old_root: str) -> None:
        g1, g2 = h.groups.get(cid1), h.groups.get(cid2)
        if g1 is None or g2 is None or g1.tainted or g2.tainted:
            reason = (g1.tainted if g1 is not None and g1.tainted else
                      g2.tainted if g2 is not None and g2.tainted else "no history")
            h.drop_group(cid1)
            h.drop_group(cid2)
            h.groups[cid1] = Group(tainted=reason)
            return
        ids = h.group_vars(cid2)
        kinds = h.vars["kind"][ids]
        in_root2 = relin.transform(g2.world, h.vars["est"][ids], kinds, invert=True)
        m = self._edge_means(cid1, [old_root])[0]
        in_root1 = relin.transform(m, in_root2, kinds)
        h.merge_groups(cid1, cid2, relin.transform(g1.world, in_root1, kinds))

    def _automatic(self, h: FactorHistory, cid: int, r: UpdateResult) -> RelinReport | None:
        """The policy's relinearisation after an applied input, if one is due."""
        p, g = self.policy, h.groups.get(cid)
        if p is None or g is None or g.tainted:
            return None
        v = r.verdict
        if (r.kind == "loop_closure" and p.nis is not None and g.since >= p.gap
                and v.dof > 0 and v.nis is not None and v.nis > chi2_quantile(p.nis, v.dof)):
            return relinearize(self, [cid], "nis")
        if p.every is not None and g.since >= p.every:
            return relinearize(self, [cid], "every")
        if p.readmit is not None:
            h.age_pending(p.readmit)
            if (r.kind == "loop_closure" and g.since >= p.gap and not p.recentre
                    and len(self._gate_fail) == REGATE_WINDOW and not any(self._gate_fail)
                    and len(h.pending_of(cid))):
                report = relinearize(self, [cid], "readmit")
                left = np.ones(h.pending.n, dtype=bool)
                left[h.pending_of(cid)] = False
                h.pending.keep(left)
                # a solve that admitted nothing left the map as it was: nothing to report
                if any(c.readmitted for c in report.components):
                    return report
        if p.recentre and r.kind == "loop_closure":
            return recentre(self, [cid])
        return None

    def _can_regate(self, cid: int, trusted: bool) -> bool:
        """A closure failed the gate: relinearise first? (the policy's ``regate``: enough
        failures among the last gated closures, this one included, and ``gap`` inputs since
        the component's last relinearisation)."""
        h, p = self.factor_history, self.policy
        if trusted or h is None or p is None or p.regate is None:
            return False
        if sum(self._gate_fail[-(REGATE_WINDOW - 1):]) + 1 < p.regate:
            return False
        g = h.groups.get(cid)
        return g is not None and g.since >= p.gap and not why_not(self, cid)

    def relinearize(self, frame: str | None = None) -> RelinReport:
        """Relinearise ``frame``'s component, or every component (oldest first): solve for
        the maximum a posteriori estimate of everything it has seen and redraw its samples
        around it with the posterior's joint covariance (:mod:`mcsm.core.relinearize`).
        Components that cannot be (an imported submap, no history) or whose solve fails (then
        unchanged) are reported as skipped, with the reason.

        Raises
        ------
        UnknownFrame
            If ``frame`` is not in the map.
        """
        cids = [self._cid(frame)] if frame is not None else sorted(self._comps)
        return relinearize(self, cids, "request")

    def remove(self, frame: str) -> RemoveResult:
        h = self.factor_history
        cid = self._cid(frame)
        g = None if h is None else h.groups.get(cid)
        if h is None or g is None:
            return super().remove(frame)
        c = self._comps[cid]
        if len(c) == 1:
            rr = super().remove(frame)
            h.drop_group(cid)
            return rr
        if g.tainted or frame not in h.var_of:
            return super().remove(frame)
        est = self._means_world(cid, [frame])[0]
        new_root = None
        if c.index[frame] == 0:
            full = [k for k in range(1, len(c)) if not c.is_point(k)]
            new_root = self._means_world(cid, [c.frames[full[0] if full else 1]])[0]
        rr = super().remove(frame)
        h.retire(frame, est)
        if new_root is not None:
            g.world = new_root
        return rr

    def import_component(self, submap: Submap) -> UpdateResult:
        r = super().import_component(submap)
        h = self.factor_history
        if h is not None:
            h.groups[self._where[r.component]] = Group(
                tainted="holds an imported submap (an import carries no history)")
        return r

    def _loop_closure(self, a: str, b: str, x: Array, x_rows: Array, point: bool,
                      trusted: bool) -> UpdateResult:
        cid = self._where[a]
        c = self._comps[cid]
        ia, ib = c.index[a], c.index[b]
        prep = joint.prepare(c, ia, ib, x_rows, point, self.space, self.analysis)
        verdict = self._verdict(prep, trusted)
        report = None
        if verdict.status == "rejected" and self._can_regate(cid, trusted):
            before = verdict.nis
            h = self.factor_history
            if h is not None and h.pending.n:  # refusals kept for re-admission: a burst
                h.pending["burst"][h.pending_of(cid, burst_only=False)] = 1
            report = relinearize(self, [cid], "gate")
            prep = joint.prepare(c, ia, ib, x_rows, point, self.space, self.analysis)
            verdict = self._verdict(prep, trusted)
            verdict = replace(verdict, reason="; ".join(
                r for r in (f"relinearised first (NIS was {before:.4g})", verdict.reason) if r))
        self._gate_observed(verdict)
        if verdict.status == "rejected":
            return UpdateResult("rejected", c.root, (), verdict, report)
        if self.method == "paper":
            if not isinstance(c, Component):  # refused at construction
                raise InvalidOperation("method='paper' runs on the CPU only")
            if self.space == "tangent":
                self._comps[cid] = paper_update_tangent(
                    c, a, b, x_rows, point,
                    lambda fn, m: joint.run_ranges(fn, m, self.threads))
            else:
                self._comps[cid] = paper_update(c, a, b, x, point, self.space)
            return UpdateResult("loop_closure", a, (), verdict, report)
        inflation, nis_avg = joint.inflation_factor(prep, self.inflation, self._nis_avg)
        self._spare = joint.apply(c, ia, ib, prep, space=self.space, gain=self.gain,
                                  shrink=self.shrink, inflation=inflation, threads=self.threads,
                                  spare=self._spare, means=recentring(self))
        self._nis_avg = nis_avg
        return UpdateResult("loop_closure", c.root, (), verdict, report)

    def gate_factor(self) -> float:
        """The gate's current scale: the median of the recent gated closures' NIS over the
        chi-square median, over ``open``, clipped to [1, max] (1 without ``gate_scale``)."""
        if self.gate_scale is None or not self._gate_u:
            return 1.0
        return min(max(median(self._gate_u) / self.gate_scale["open"], 1.0),
                   self.gate_scale["max"])

    def _verdict(self, prep: joint.Prepared, trusted: bool) -> Verdict:
        nis, dof = prep.nis, prep.dof
        if self.gate is None or dof == 0:
            return Verdict("accepted", nis, dof, None,
                           "no gate" if self.gate is None else "nothing varies: no test")
        scale, learnt = self.gate_factor(), self.learnt_factor()
        why = f"gate scaled x{scale:.3g} by the recent NIS" if scale > 1.0 else ""
        if learnt > scale:
            scale, why = learnt, f"gate scaled x{learnt:.3g} by the closures admitted later"
        threshold = chi2_quantile(self.gate, dof) * scale
        if trusted:
            return Verdict("accepted", nis, dof, threshold, "trusted: gate bypassed")
        status = "rejected" if not nis <= threshold else "accepted"
        return Verdict(status, nis, dof, threshold, why)

    def learnt_factor(self) -> float:
        """``Policy.calibrate``'s scale: the lower quartile of the last K arrival ratios (NIS
        over the unscaled threshold) of refused closures admitted later, clipped to [1, max]
        (1 without it, or before it has 3 of them)."""
        p, h = self.policy, self.factor_history
        if p is None or p.calibrate is None or h is None or len(h.admitted_u) < 3:
            return 1.0
        q = lower_quantile(h.admitted_u[-p.calibrate:], CALIBRATE_QUANTILE)
        return min(max(q, 1.0), self.gate_scale["max"] if self.gate_scale is not None else 30.0)

    def _gate_observed(self, verdict: Verdict) -> None:
        """Put a gated closure's NIS into the gate scale's window and its outcome into the
        policy's window of failures."""
        if verdict.threshold is None or verdict.dof == 0 or verdict.nis is None:
            return  # no gate, or nothing to test (trusted closures count as accepted)
        if self._track_fail:
            self._gate_fail.append(int(verdict.status == "rejected"))
            del self._gate_fail[: max(0, len(self._gate_fail) - REGATE_WINDOW)]
        if self.gate_scale is not None:
            self._gate_u.append(verdict.nis / chi2_quantile(0.5, verdict.dof))
            del self._gate_u[: max(0, len(self._gate_u) - int(self.gate_scale["window"]))]


__all__ = ["StochasticMap", "DEFAULT_GATE", "DEFAULT_POLICY", "UpdateResult", "RemoveResult",
           "Submap", "Verdict", "Policy", "RelinReport", "check_frame_name", "default_threads"]
