"""The map's factor history: a compact record of every constraint the map applied, for
relinearisation (:mod:`mcsm.core.relinearize`).

One *variable* per frame incarnation (a frame removed and added again is a new variable), with
its kind (pose or point), its component (*group*, the component's id), whether the frame is
still in the map, and its current estimate (removed frames keep theirs) in the group's *world*
frame: the root frame of the component when the group began; ``world`` of a group is the pose
of its current root in that frame, so that re-rooting costs O(1). One *factor* per accepted
input (new frames, joins and loop closures alike; rejected closures are not in it): its two
variables, pose or point, the input's mean and packed square-root information in the
project's chart (:func:`mcsm.core.relin.moments`), and whether the gate passed it as a loop
closure (a closure forced in beyond the gate is never left out by a relinearisation).
*Pending* (only with ``Policy.readmit``): the recent closures the gate refused, in the same
form, which a later relinearisation may admit as factors.
*Priors*: dense Gaussian factors on the variables that marginalised old removed variables
touched (:mod:`mcsm.core.relinearize` writes them when the history outgrows its bound).

Everything is in numpy arrays with amortised growth (about 240 bytes per factor and 70 per
variable); it is part of the map's snapshot and state digest. Imported submaps carry no
history: their component is *tainted* (not relinearised) until it is gone.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

Array = npt.NDArray[np.float64]

FACTOR_BYTES = 4 + 1 + 8 + 7 * 8 + 21 * 8
VAR_BYTES = 4 + 8 + 1 + 7 * 8
IDENTITY = np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])

_VAR_COLS: dict[str, tuple[Any, tuple[int, ...]]] = {
    "kind": (np.int32, ()), "group": (np.int64, ()), "alive": (np.uint8, ()),
    "est": (np.float64, (7,))}
_FAC_COLS: dict[str, tuple[Any, tuple[int, ...]]] = {
    "kind": (np.int32, ()), "robust": (np.uint8, ()), "vars": (np.int32, (2,)),
    "z": (np.float64, (7,)), "w": (np.float64, (21,))}
_PEND_COLS: dict[str, tuple[Any, tuple[int, ...]]] = {
    "kind": (np.int32, ()), "vars": (np.int32, (2,)), "z": (np.float64, (7,)),
    "w": (np.float64, (21,)), "at": (np.int64, ()), "burst": (np.uint8, ()),
    "u": (np.float64, ())}
ADMITTED_KEEP = 64
"""How many arrival ratios of refused closures admitted later the history keeps
(``Policy.calibrate`` reads the last K of them)."""


class Table:
    """Columns of one length with amortised growth (capacity doubles)."""

    def __init__(self, cols: dict[str, tuple[Any, tuple[int, ...]]]) -> None:
        self._cols = cols
        self.n = 0
        self._data = {k: np.zeros((4, *shape), dtype=dt) for k, (dt, shape) in cols.items()}

    def __getitem__(self, key: str) -> Any:
        return self._data[key][: self.n]

    def append(self, **values: Any) -> int:
        if self.n == len(self._data["kind"]):
            for k, a in self._data.items():
                b = np.zeros((2 * len(a), *a.shape[1:]), dtype=a.dtype)
                b[: self.n] = a[: self.n]
                self._data[k] = b
        for k, v in values.items():
            self._data[k][self.n] = v
        self.n += 1
        return self.n - 1

    def keep(self, mask: npt.NDArray[np.bool_]) -> None:
        """Keep the rows where ``mask`` is true (in order), in place: the capacity stays, so a
        history at its bound reuses its memory instead of allocating it again."""
        rows = np.flatnonzero(mask)
        for a in self._data.values():
            a[: len(rows)] = a[rows]
        self.n = len(rows)

    def to_plain(self) -> dict[str, Any]:
        return {"n": self.n, **{k: np.ascontiguousarray(self[k]).astype(
            np.dtype(self._cols[k][0]).newbyteorder("<")).tobytes() for k in self._cols}}

    def load(self, d: dict[str, Any]) -> None:
        self.n = int(d["n"])
        for k, (dt, shape) in self._cols.items():
            if k not in d:  # a column added later (the pending table's "u"): zeros
                self._data[k] = np.zeros((max(4, self.n), *shape), dtype=dt)
                continue
            a = np.frombuffer(d[k], dtype=np.dtype(dt).newbyteorder("<")).astype(dt)
            a = a.reshape((self.n, *shape))
            b = np.zeros((max(4, self.n), *shape), dtype=dt)
            b[: self.n] = a
            self._data[k] = b


@dataclass
class Prior:
    """A dense Gaussian factor: ``vars`` (anchor first), error ``R c + d`` where ``c`` stacks
    the charts of ``anchor⁻¹ ∘ x_j`` around ``zhat_j``."""

    vars: npt.NDArray[np.int32]
    zhat: Array
    r: Array
    d: Array

    @property
    def nbytes(self) -> int:
        return int(self.vars.nbytes + self.zhat.nbytes + self.r.nbytes + self.d.nbytes)

    def to_plain(self) -> dict[str, Any]:
        return {"vars": self.vars.astype("<i4").tobytes(),
                "zhat": self.zhat.astype("<f8").tobytes(),
                "rows": int(self.r.shape[0]), "cols": int(self.r.shape[1]),
                "r": self.r.astype("<f8").tobytes(), "d": self.d.astype("<f8").tobytes()}

    @classmethod
    def from_plain(cls, d: dict[str, Any]) -> Prior:
        v = np.frombuffer(d["vars"], dtype="<i4").astype(np.int32)
        rows, cols = int(d["rows"]), int(d["cols"])
        return cls(v, np.frombuffer(d["zhat"], dtype="<f8").reshape(len(v) - 1, 7).copy(),
                   np.frombuffer(d["r"], dtype="<f8").reshape(rows, cols).copy(),
                   np.frombuffer(d["d"], dtype="<f8").copy())


@dataclass
class Group:
    """One component's history bookkeeping."""

    world: Array = field(default_factory=lambda: IDENTITY.copy())
    since: int = 0          # inputs since the last relinearisation
    tainted: str = ""       # why this component is not relinearised ("" if it is)

    def to_plain(self) -> dict[str, Any]:
        return {"world": self.world.astype("<f8").tobytes(), "since": self.since,
                "tainted": self.tainted}

    @classmethod
    def from_plain(cls, d: dict[str, Any]) -> Group:
        return cls(np.frombuffer(d["world"], dtype="<f8").copy(), int(d["since"]),
                   str(d["tainted"]))


class FactorHistory:
    """The record (see the module docstring); ``bound_bytes`` is the size beyond which the
    oldest removed variables are marginalised (:meth:`nbytes`)."""

    def __init__(self, bound_bytes: int) -> None:
        self.bound_bytes = int(bound_bytes)
        self.vars = Table(_VAR_COLS)
        self.factors = Table(_FAC_COLS)
        self.priors: list[Prior] = []
        self.groups: dict[int, Group] = {}
        self.var_of: dict[str, int] = {}     # alive frame -> variable
        self.frame_of: dict[int, str] = {}   # alive variable -> frame
        self.n_inputs = 0                    # factors ever added (the generator's key)
        self.n_relin = 0                     # relinearisations run
        self.n_marginalised = 0              # variables marginalised into priors
        self.pending = Table(_PEND_COLS)     # refused closures kept for re-admission
        self.n_readmitted = 0                # refused closures admitted later
        self.admitted_u: list[float] = []    # their arrival ratios (``Policy.calibrate``)

    # ------------------------------------------------------------------ size
    def nbytes(self) -> int:
        return (self.factors.n * FACTOR_BYTES + self.vars.n * VAR_BYTES
                + sum(p.nbytes for p in self.priors))

    def over_bound(self) -> bool:
        return self.nbytes() > self.bound_bytes

    # ------------------------------------------------------------------ variables
    def new_var(self, frame: str, point: bool, group: int, est_world: Array) -> int:
        v = self.vars.append(kind=1 if point else 0, group=group, alive=1, est=est_world)
        self.var_of[frame] = v
        self.frame_of[v] = frame
        return v

    def add_factor(self, point: bool, a: int, b: int, z: Array, w: Array,
                   robust: bool = False) -> None:
        """A factor; ``robust``: a loop closure the gate judged (a relinearisation may leave
        it out when the whole history contradicts it)."""
        self.factors.append(kind=1 if point else 0, robust=int(robust), vars=(a, b), z=z, w=w)
        self.n_inputs += 1

    def add_pending(self, point: bool, a: int, b: int, z: Array, w: Array,
                    u: float = 0.0) -> None:
        """A loop closure the gate refused, kept for re-admission (``Policy.readmit``);
        ``u``: its NIS over the gate's unscaled threshold when it was refused."""
        self.pending.append(kind=1 if point else 0, vars=(a, b), z=z, w=w, at=self.n_inputs,
                            burst=0, u=u)

    def age_pending(self, window: int) -> None:
        """Forget the refused closures older than ``window`` inputs."""
        if self.pending.n:
            self.pending.keep(self.n_inputs - self.pending["at"] <= window)

    def pending_of(self, cid: int, burst_only: bool = True) -> npt.NDArray[np.int64]:
        """Rows of the refused closures kept for component ``cid`` (marked ones only)."""
        if not self.pending.n:
            return np.zeros(0, dtype=np.int64)
        sel = self.vars["group"][self.pending["vars"][:, 0]] == cid
        if burst_only:
            sel &= self.pending["burst"] != 0
        return np.flatnonzero(sel)

    def retire(self, frame: str, est_world: Array) -> None:
        """``frame`` left the map: its variable keeps ``est_world``."""
        v = self.var_of.pop(frame)
        del self.frame_of[v]
        self.vars["alive"][v] = 0
        self.vars["est"][v] = est_world

    def group_vars(self, cid: int) -> npt.NDArray[np.int64]:
        return np.flatnonzero(self.vars["group"] == cid)

    def drop_group(self, cid: int) -> None:
        """Forget a component's whole history (the component is gone, or tainted)."""
        gone = self.vars["group"] == cid
        if np.any(gone):
            self._delete_vars(gone)
        self.groups.pop(cid, None)

    def _delete_vars(self, gone: npt.NDArray[np.bool_]) -> None:
        """Delete variables (and every factor and prior touching them), renumbering the rest."""
        new_id = np.cumsum(~gone) - 1
        fv = self.factors["vars"]
        keep_f = ~(gone[fv[:, 0]] | gone[fv[:, 1]]) if self.factors.n else np.zeros(0, bool)
        self.factors.keep(keep_f)
        if self.factors.n:
            self.factors["vars"][:] = new_id[self.factors["vars"]]
        kept_priors = []
        for p in self.priors:
            if not np.any(gone[p.vars]):
                p.vars = new_id[p.vars].astype(np.int32)
                kept_priors.append(p)
        self.priors = kept_priors
        if self.pending.n:
            pv = self.pending["vars"]
            self.pending.keep(~(gone[pv[:, 0]] | gone[pv[:, 1]]))
            if self.pending.n:
                self.pending["vars"][:] = new_id[self.pending["vars"]]
        for v in np.flatnonzero(gone):
            f = self.frame_of.pop(int(v), None)
            if f is not None:
                del self.var_of[f]
        self.frame_of = {int(new_id[v]): f for v, f in self.frame_of.items()}
        self.var_of = {f: v for v, f in self.frame_of.items()}
        self.vars.keep(~gone)

    def merge_groups(self, into: int, other: int, moved: Array) -> None:
        """Component ``other`` joined ``into``: its variables' estimates become
        ``moved`` (already in ``into``'s world frame)."""
        g1, g2 = self.groups[into], self.groups.pop(other)
        ids = self.group_vars(other)
        self.vars["group"][ids] = into
        self.vars["est"][ids] = moved
        g1.since += g2.since
        if g2.tainted and not g1.tainted:
            g1.tainted = g2.tainted

    # ------------------------------------------------------------------ snapshot, digest
    def to_plain(self) -> dict[str, Any]:
        d: dict[str, Any] = {"bound_bytes": self.bound_bytes, "vars": self.vars.to_plain(),
                             "factors": self.factors.to_plain(),
                             "priors": [p.to_plain() for p in self.priors],
                             "groups": {str(c): g.to_plain()
                                        for c, g in sorted(self.groups.items())},
                             "frames": [[v, f] for v, f in sorted(self.frame_of.items())],
                             "counters": [self.n_inputs, self.n_relin, self.n_marginalised]}
        if self.pending.n or self.n_readmitted:  # only with Policy.readmit
            d["pending"] = self.pending.to_plain()
            d["n_readmitted"] = self.n_readmitted
        if self.admitted_u:  # only with Policy.calibrate
            d["admitted_u"] = np.asarray(self.admitted_u, dtype="<f8").tobytes()
        return d

    @classmethod
    def from_plain(cls, d: dict[str, Any]) -> FactorHistory:
        h = cls(int(d["bound_bytes"]))
        h.vars.load(d["vars"])
        h.factors.load(d["factors"])
        h.priors = [Prior.from_plain(p) for p in d["priors"]]
        h.groups = {int(c): Group.from_plain(g) for c, g in d["groups"].items()}
        h.frame_of = {int(v): str(f) for v, f in d["frames"]}
        h.var_of = {f: v for v, f in h.frame_of.items()}
        h.n_inputs, h.n_relin, h.n_marginalised = (int(c) for c in d["counters"])
        if "pending" in d:
            h.pending.load(d["pending"])
            h.n_readmitted = int(d["n_readmitted"])
        if "admitted_u" in d:
            h.admitted_u = np.frombuffer(d["admitted_u"], dtype="<f8").tolist()
        return h

    def digest_update(self, h: Any, calibrated: bool = False) -> None:
        """Hash the whole record into ``h`` (hashlib), in a fixed order; the arrival ratios
        (the pending table's ``u`` and ``admitted_u``) only with ``calibrated`` (maps
        without ``Policy.calibrate`` keep the digests they had before it)."""
        plain = self.to_plain()
        for table in ("vars", "factors"):
            t = plain[table]
            h.update(str(t["n"]).encode())
            for k in sorted(t):
                if k != "n":
                    h.update(t[k])
        for p in plain["priors"]:
            for k in ("vars", "zhat", "r", "d"):
                h.update(p[k])
        for c, g in plain["groups"].items():
            h.update(f"{c}:{g['since']}:{g['tainted']}".encode())
            h.update(g["world"])
        h.update(repr(plain["frames"]).encode())
        h.update(repr(plain["counters"] + [self.bound_bytes]).encode())
        if "pending" in plain:
            t = plain["pending"]
            h.update(f"pending {t['n']} {plain['n_readmitted']}".encode())
            for k in sorted(t):
                if k != "n" and (k != "u" or calibrated):
                    h.update(t[k])
        if calibrated:
            h.update(np.asarray(self.admitted_u, dtype="<f8").tobytes())


__all__ = ["ADMITTED_KEEP", "FactorHistory", "Group", "Prior", "Table", "FACTOR_BYTES",
           "VAR_BYTES"]
