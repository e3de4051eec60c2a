"""The Monte Carlo stochastic map (PAPER §3): the public facade of the core.

:class:`StochasticMap` keeps the map's options and dispatches an update to the forest's
structure (new frame, new component, join: :mod:`mcsm.core.forest`) or, for a loop closure
(case II), to the joint update (:mod:`mcsm.core.joint`, the default, compiled and portable)
or the paper's own update (:mod:`mcsm.core.paper`, machine-bound, kept for reproduction).
A loop closure can be gated first: its normalised innovation against the map's prediction is
compared with a chi-square quantile (:mod:`mcsm.core.gate`); a rejected one leaves the map
unchanged and says so in :attr:`UpdateResult.verdict`.

Every refused call raises an :class:`mcsm.errors.McsmError` and leaves the map bit-identical.
"""

from __future__ import annotations

import json
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from mcsm.core import joint
from mcsm.core.at import check_samples
from mcsm.core.device import backend_for
from mcsm.core.forest import (
    Forest,
    RemoveResult,
    Submap,
    UpdateResult,
    Verdict,
    check_frame_name,
)
from mcsm.core.gate import chi2_quantile
from mcsm.core.paper import paper_update, paper_update_tangent
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
        self.threads = default_threads() if threads is None else threads
        self._spare: Array | None = None  # the buffer the last joint update replaced

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
        ``gate`` is left out when it is None, so a map without a gate has the options (and
        digest) it had before the gate existed."""
        o: dict[str, Any] = {"n_samples": self.n_samples, "method": self.method,
                             "space": self.space, "analysis": self.analysis,
                             "shrink": self.shrink, "inflation": self.inflation,
                             "gain": self.gain}
        if self.gate is not None:
            o["gate"] = self.gate
        return o

    @classmethod
    def from_options(cls, options: dict[str, Any], device: object = "cpu") -> StochasticMap:
        """Build an empty map from :meth:`options` output (as recorded). A missing ``gate``
        means no gate: the options of a map recorded before the gate's default changed, or
        of one without a gate (:meth:`options` leaves it out), rebuild that map."""
        o = dict(options)
        n = o.pop("n_samples")
        o.setdefault("gate", None)
        return cls(int(n), **o, device=device)

    def _digest_header(self, h: Any) -> None:
        h.update(json.dumps(self.options(), sort_keys=True).encode())
        if self.inflation == "adaptive":
            h.update(np.float64(self._nis_avg).tobytes())

    def snapshot(self) -> dict[str, Any]:
        """The whole state (options, structure, edges, adaptive-inflation average) as plain
        values and arrays; :meth:`from_snapshot` rebuilds a map with the same digest."""
        return {"options": self.options(), "nis_avg": self._nis_avg, **super().snapshot()}

    @classmethod
    def from_snapshot(cls, snap: dict[str, Any], threads: int | None = None,
                      device: object = "cpu") -> StochasticMap:
        m = cls.from_options({**dict(snap["options"]), "threads": threads}, device=device)
        m.restore_snapshot(snap)
        m._nis_avg = float(snap["nis_avg"])
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

        if not has_a and not has_b:
            return self._new_component(a, b, x_rows, point)
        if has_a and not has_b:
            return self._add_leaf(a, b, x_rows, point, inverse=False)
        if not has_a:
            if point:
                raise InvalidOperation(
                    f"a point observation cannot place the unknown observer {a!r}")
            return self._add_leaf(b, a, x_rows, point, inverse=True)
        if self._where[a] != self._where[b]:
            return self._join(a, b, x_rows, point)
        return self._loop_closure(a, b, x, x_rows, point, trusted)

    def _loop_closure(self, a: str, b: str, x: Array, x_rows: Array, point: bool,
                      trusted: bool) -> UpdateResult:
        cid = self._where[a]
        c = self._comps[cid]
        ia, ib = c.index[a], c.index[b]
        prep = joint.prepare(c, ia, ib, x_rows, point, self.space, self.analysis)
        verdict = self._verdict(prep, trusted)
        if verdict.status == "rejected":
            return UpdateResult("rejected", c.root, (), verdict)
        if self.method == "paper":
            if not isinstance(c, Component):  # refused at construction
                raise InvalidOperation("method='paper' runs on the CPU only")
            if self.space == "tangent":
                self._comps[cid] = paper_update_tangent(
                    c, a, b, x_rows, point,
                    lambda fn, m: joint.run_ranges(fn, m, self.threads))
            else:
                self._comps[cid] = paper_update(c, a, b, x, point, self.space)
            return UpdateResult("loop_closure", a, (), verdict)
        inflation, nis_avg = joint.inflation_factor(prep, self.inflation, self._nis_avg)
        self._spare = joint.apply(c, ia, ib, prep, space=self.space, gain=self.gain,
                                  shrink=self.shrink, inflation=inflation,
                                  threads=self.threads, spare=self._spare)
        self._nis_avg = nis_avg
        return UpdateResult("loop_closure", c.root, (), verdict)

    def _verdict(self, prep: joint.Prepared, trusted: bool) -> Verdict:
        nis, dof = prep.nis, prep.dof
        if self.gate is None:
            return Verdict("accepted", nis, dof, None, "no gate")
        if dof == 0:
            return Verdict("accepted", nis, dof, None, "nothing varies: no test")
        threshold = chi2_quantile(self.gate, dof)
        if trusted:
            return Verdict("accepted", nis, dof, threshold, "trusted: gate bypassed")
        status = "rejected" if not nis <= threshold else "accepted"
        return Verdict(status, nis, dof, threshold, "")


__all__ = ["StochasticMap", "DEFAULT_GATE", "UpdateResult", "RemoveResult", "Submap",
           "Verdict", "check_frame_name", "default_threads"]
