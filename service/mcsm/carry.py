"""What a recorded state snapshot carries: the map, the remembered request ids, the retract
window.

A ``/mcsm/snapshot`` record (``schemas/record_snapshot.json``) holds a map's whole state after
one operation. ``--restore`` and a split recording's files start from one, so it also carries
what exactly-once and ``retract`` need to go on as if nothing had happened:

* ``state``: :meth:`StochasticMap.snapshot` with its edges as raw float64
  (:func:`encode_snapshot`; the layout of the rest is the core's, opaque here);
* ``ids``: the request ids the map remembers (:meth:`MapState.id_columns`), as columns
  (:func:`encode_ids`): ids, seqs, operations, 128-bit request fingerprints and receive
  times (binary columns, no per-id object when written), so that a retry of any of them is
  answered ``duplicate`` after a restore, however many restores or split files lie in
  between, and ``--id-ttl-s`` still counts from the original receive time;
* ``window`` (in a snapshot its file starts from, a split or a restored file's, when the
  map's retract window reaches back before it): the window's snapshots and logged requests
  (:func:`encode_window`), so that a file replayed alone, or a server restored from it, can
  retract exactly what the live server could.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from mcsm import ops, wire
from mcsm.deferral import DeferState
from mcsm.errors import McsmError
from mcsm.history import History, Logged
from mcsm.idmemory import IdColumns

WINDOW_FORMAT = 1
"""Version of the ``window`` layout of a snapshot record."""
_FP_BYTES = 16  # a request fingerprint: 32 hex digits


def encode_snapshot(snap: dict[str, Any]) -> dict[str, Any]:
    """A :meth:`StochasticMap.snapshot` as msgpack-able values (edges as raw float64)."""
    return {**{k: v for k, v in snap.items() if k != "components"},
            "components": [{**{k: v for k, v in c.items() if k != "edges"},
                            "edges": wire.pack_array(c["edges"])}
                           for c in snap["components"]]}


def decode_snapshot(obj: Any, n_samples: int) -> dict[str, Any]:
    """Inverse of :func:`encode_snapshot`, checked (shapes, finiteness).

    Raises
    ------
    McsmError
        If the record is not a snapshot of a map with ``n_samples`` samples.
    """
    if not isinstance(obj, dict) or not isinstance(obj.get("components"), list):
        raise McsmError("a snapshot record without components")
    comps = []
    for c in obj["components"]:
        if not isinstance(c, dict):
            raise McsmError("a snapshot component is not a map")
        edges = wire.unpack_array(c.get("edges"), "edges", 3, max_elems=1 << 27)
        if edges.shape[1:] != (n_samples, 7):
            raise McsmError(f"snapshot edges {edges.shape} do not fit N = {n_samples}")
        comps.append({**c, "edges": edges})
    return {**obj, "components": comps}


def encode_ids(c: IdColumns) -> dict[str, Any]:
    """The remembered ids (:meth:`MapState.id_columns`, oldest first) as msgpack-able
    columns: about 45 bytes plus the id per remembered request, built without a Python
    object per id."""
    return {"id": c.ids, "id_len": np.asarray(c.lens, dtype="<u2").tobytes(),
            "seq": np.asarray(c.seq, dtype="<i8").tobytes(), "op_names": list(c.op_names),
            "op": np.asarray(c.op, dtype="u1").tobytes(), "fp": bytes(c.fp),
            "time_ns": np.asarray(c.time_ns, dtype="<i8").tobytes()}


def decode_ids(obj: Any) -> list[list[Any]]:
    """Inverse of :func:`encode_ids`, checked, as :meth:`MapState.export_ids` rows.

    Raises
    ------
    McsmError
        If the columns do not fit together.
    """
    try:
        lens = np.frombuffer(bytes(obj["id_len"]), dtype="<u2")
        c = IdColumns(bytes(obj["id"]), lens, np.frombuffer(bytes(obj["seq"]), dtype="<i8"),
                      [str(x) for x in obj["op_names"]],
                      np.frombuffer(bytes(obj["op"]), dtype="u1"), bytes(obj["fp"]),
                      np.frombuffer(bytes(obj["time_ns"]), dtype="<i8"))
    except (KeyError, TypeError, ValueError) as exc:
        raise McsmError(f"unreadable remembered ids: {exc}") from None
    n = lens.size
    if not (c.seq.size == c.op.size == c.time_ns.size == n and len(c.fp) == _FP_BYTES * n
            and int(lens.sum()) == len(c.ids)
            and (n == 0 or int(c.op.max()) < len(c.op_names))):
        raise McsmError("remembered ids: columns of different lengths")
    try:
        return c.rows()
    except UnicodeDecodeError as exc:
        raise McsmError(f"remembered ids: {exc}") from None


def encode_window(h: History) -> dict[str, Any] | None:
    """The retract window ``h`` as msgpack-able values, or None when some logged input has no
    recorded bytes (applied in-process without ``payload``), so it cannot be carried."""
    if any(e.payload is None for e in h.log):
        return None
    return {"format": WINDOW_FORMAT, "dropped_before": h.dropped_before,
            "snapshots": [{"seq": seq, "state": encode_snapshot(snap), "bytes": size,
                           "deferral": None if dfr is None else dfr.encode()}
                          for seq, snap, dfr, size in h.snapshots],
            "log": [{"seq": e.seq, "op": e.op, "id": e.request_id, "request": e.payload,
                     "verdict": None if e.verdict is None else e.verdict.to_dict(),
                     "retracted": e.retracted, "bytes": e.nbytes} for e in h.log]}


def decode_window(obj: Any, h: History, n_samples: int) -> None:
    """Load the window :func:`encode_window` wrote into ``h`` (whose options come from the
    map's recorded config).

    Raises
    ------
    McsmError
        If the record does not hold a window of a map with ``n_samples`` samples.
    """
    if not isinstance(obj, dict) or obj.get("format") != WINDOW_FORMAT:
        raise McsmError("a retract window of an unknown format")
    try:
        snaps = [(int(s["seq"]), decode_snapshot(s["state"], n_samples),
                  None if s.get("deferral") is None
                  else DeferState.decode(s["deferral"], n_samples), int(s["bytes"]))
                 for s in obj["snapshots"]]
        log = [Logged(int(e["seq"]), str(e["op"]), str(e["id"]), None,
                      None if e.get("verdict") is None else wire.Verdict.from_dict(e["verdict"]),
                      bool(e["retracted"]), int(e["bytes"]), bytes(e["request"]), n_samples)
               for e in obj["log"]]
        dropped = int(obj["dropped_before"])
    except (KeyError, TypeError, ValueError) as exc:
        raise McsmError(f"unreadable retract window: {exc}") from None
    h.snapshots, h.log, h.dropped_before = snaps, log, dropped
    h.by_id = {e.request_id: e for e in log if ops.get(e.op).change is not None}


__all__ = ["encode_snapshot", "decode_snapshot", "encode_ids", "decode_ids", "encode_window",
           "decode_window", "WINDOW_FORMAT"]
