"""The one table of operations: every request the server answers, named once.

Each :class:`Operation` says everything the rest of the code needs to know about one request:
its key leaf (``<prefix>/<map>/<leaf>``, optionally ``/<namespace>``), its request and reply
dataclasses, the wire decoder (server, replay) and encoder (clients), and, for an operation
that changes the map, its recording topic, what it does to the map, how its event names the
frames, and what its idempotency fingerprint covers. Read-only operations carry the function
that answers them instead.

The server routes and decodes with :func:`decode_request`, answers or applies by looking the
operation up in :data:`OPS`; :class:`mcsm.state.MapState` applies through :attr:`Operation.
change`; the recorder and replay take their topics from :data:`INPUT_TOPICS`; the client builds
its requests from the table. Adding an operation is one entry here (plus its wire dataclass and
codec, its schema, and a client method); see CONTRIBUTING.md.

Imports point one way: this module needs :mod:`mcsm.wire` and :mod:`mcsm.errors` only (the
map and the server's state are passed in), so clients may import it.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from mcsm import wire
from mcsm.core.names import is_namespace, namespace_of
from mcsm.deferral import gated_update
from mcsm.errors import BadMessage, Forbidden, McsmError, UnknownFrame

if TYPE_CHECKING:
    from mcsm.core.smap import StochasticMap
    from mcsm.state import MapState


@dataclass(frozen=True)
class Change:
    """What a state-changing operation did to the map (the core's result, for the ack)."""

    kind: str
    component: str | None
    frames_added: tuple[str, ...] = ()
    frames_removed: tuple[str, ...] = ()
    verdict: wire.Verdict | None = None
    relin: dict[str, Any] | None = None
    """The relinearisation it ran (:meth:`mcsm.core.relinearize.RelinReport.to_dict`)."""


class Context(Protocol):
    """What a read-only operation's answer may ask of the server."""

    server_id: str

    def info(self, st: MapState) -> wire.MapInfo: ...


def _no_check(req: Any, namespace: str, key: str) -> None:
    del req, namespace, key


def _no_map_check(st: MapState, req: Any, namespace: str, key: str) -> None:
    del st, req, namespace, key


def _frames_of_ack(req: Any, ack: wire.Ack) -> tuple[str, ...]:
    del req
    return ack.frames_added or ack.frames_removed


def _no_extra(st: MapState, req: Any) -> dict[str, Any]:
    del st, req
    return {}


@dataclass(frozen=True)
class Operation:
    """One operation of the table (see the module docstring)."""

    name: str
    """The operation's name: in acks, events, recordings and logs."""
    leaf: str
    """Its key leaf: requests go to ``<prefix>/<map>/<leaf>``."""
    request: type
    """The request dataclass the decoder returns (``isinstance`` picks the operation when
    two share a leaf: ``submap`` carries export and import)."""
    decode: Callable[[bytes, int], Any]
    """``decode(payload, n_samples)``: the checked request (raises ``McsmError``)."""
    encode: Callable[..., bytes]
    """``encode(request_id, ...)``: the request payload a client sends."""
    decode_reply: Callable[[bytes], Any]
    """The client's decoder of the server's reply."""
    namespaced: bool = False
    """Also served on ``<leaf>/<namespace>``, which writes only that namespace's frames."""
    check_namespace: Callable[[Any, str, str], None] = _no_check
    """``(req, namespace, key)``: refuse (``Forbidden``) a request on a namespaced key that
    touches another namespace, before it is queued."""
    check_namespace_map: Callable[[MapState, Any, str, str], None] = _no_map_check
    """The same check against the map, on the worker (e.g. a new frame ``b``)."""
    topic: str | None = None
    """Recording topic of a state-changing operation (``None``: read-only, not recorded)."""
    change: Callable[..., Change] | None = None
    """``change(smap, req, trusted=False)``: apply to the core map (live, replay and the
    retract window's rebuild all call it)."""
    retract: bool | None = None
    """True for retract, False for reinstate: the operation rewrites the retract window
    (:mod:`mcsm.history`) instead of calling ``change``."""
    retractable: bool = False
    """Inputs of this operation can be retracted and reinstated."""
    fingerprint_parts: Callable[[Any], list[bytes | memoryview]] | None = None
    """What the idempotency fingerprint covers (not the id or sender)."""
    event_frames: Callable[[Any, wire.Ack], tuple[str, ...]] = _frames_of_ack
    event_extra: Callable[[MapState, Any], dict[str, Any]] = _no_extra
    answer: Callable[[Context, MapState, Any], bytes] | None = None
    """A read-only operation's reply payload (raises ``McsmError`` to refuse)."""
    describe: Callable[[Any], dict[str, Any]] = lambda req: {}
    """The request's names as JSON-able fields (``mcsm cat``; arrays are left to the caller)."""

    @property
    def changes_state(self) -> bool:
        """Applied in sequence, recorded, acknowledged with an :class:`~mcsm.wire.Ack`."""
        return self.topic is not None


# --------------------------------------------------------------------------------------------
# The state-changing operations
# --------------------------------------------------------------------------------------------

def _update_check(req: wire.UpdateRequest, namespace: str, key: str) -> None:
    if namespace and namespace_of(req.a) != namespace:
        raise Forbidden(key, req.a, namespace, "an update observed from another namespace")


def _update_check_map(st: MapState, req: wire.UpdateRequest, namespace: str, key: str) -> None:
    if namespace and namespace_of(req.b) != namespace and not _has(st.map, req.b):
        raise Forbidden(key, req.b, namespace, "a new frame in another namespace")


def _has(smap: StochasticMap, frame: str) -> bool:
    try:
        smap.is_point(frame)
    except UnknownFrame:
        return False
    return True


def _update_change(smap: StochasticMap, req: wire.UpdateRequest, trusted: bool = False
                   ) -> Change:
    r, v = gated_update(smap, req, trusted)
    return Change(r.kind, r.component, frames_added=tuple(r.frames_added), verdict=v,
                  relin=None if r.relin is None else r.relin.to_dict())


def _update_parts(req: wire.UpdateRequest) -> list[bytes | memoryview]:
    return [f"\0{req.a}\0{req.b}\0{req.samples.shape}\0".encode(), _bytes_view(req.samples)]


def _remove_check(req: wire.RemoveRequest, namespace: str, key: str) -> None:
    if namespace and namespace_of(req.frame) != namespace:
        raise Forbidden(key, req.frame, namespace, "a remove of another namespace's frame")


def _remove_change(smap: StochasticMap, req: wire.RemoveRequest, trusted: bool = False
                   ) -> Change:
    del trusted
    rr = smap.remove(req.frame)
    return Change("remove", rr.component, frames_removed=tuple(rr.frames_removed))


def _import_change(smap: StochasticMap, req: wire.SubmapImportRequest, trusted: bool = False
                   ) -> Change:
    del trusted
    r = smap.import_component(req.submap.to_core())
    return Change(r.kind, r.component, frames_added=tuple(r.frames_added))


def _import_parts(req: wire.SubmapImportRequest) -> list[bytes | memoryview]:
    sub = req.submap
    return [f"\0{sub.root}\0{'/'.join(sub.frames)}\0{sub.is_point}\0{sub.edges.shape}\0"
            .encode(), _bytes_view(sub.edges)]


def _target_parts(req: wire.RetractRequest) -> list[bytes | memoryview]:
    return [f"\0{req.target}".encode()]


def _retract_extra(st: MapState, req: wire.RetractRequest) -> dict[str, Any]:
    """What changed: the target and the verdicts of the re-gated inputs."""
    return {"target": req.target,
            "changed": {rid: v.to_dict() for rid, v in st.last_changed.items()}}


def _relinearize_change(smap: StochasticMap, req: wire.RelinearizeRequest,
                        trusted: bool = False) -> Change:
    del trusted
    rep = smap.relinearize(req.frame or None)
    return Change("relinearize", smap.root(req.frame) if req.frame else None,
                  relin=rep.to_dict())


def _bytes_view(a: wire.Samples) -> memoryview:
    """The little-endian float64 bytes of ``a`` without a copy when it is already so."""
    return np.ascontiguousarray(a, dtype=wire.F8).data.cast("B")


# --------------------------------------------------------------------------------------------
# The read-only operations
# --------------------------------------------------------------------------------------------

def _verdict_answer(ctx: Context, st: MapState, req: wire.VerdictRequest) -> bytes:
    return wire.encode_ack(replace(st.verdict_of(req.target), server=ctx.server_id))


def _query_answer(ctx: Context, st: MapState, req: wire.QueryRequest) -> bytes:
    del ctx
    if req.want == "marginal":
        mean, cov = st.map.marginal(req.a, req.b)
        return wire.encode_query_reply(
            wire.QueryReply(req.request_id, req.a, req.b, st.seq, mean=mean, cov=cov))
    return wire.encode_query_reply(wire.QueryReply(req.request_id, req.a, req.b, st.seq,
                                                   samples=st.map.query(req.a, req.b)))


def _info_answer(ctx: Context, st: MapState, req: wire.InfoRequest) -> bytes:
    del req
    return wire.encode_info_reply(ctx.info(st))


def _export_answer(ctx: Context, st: MapState, req: wire.SubmapExportRequest) -> bytes:
    del ctx
    sub = st.map.export_component(req.frame)
    return wire.encode_submap_reply(
        wire.SubmapReply(req.request_id, st.seq, wire.submap_from_core(sub)))


def _decode_info(payload: bytes, n_samples: int) -> wire.InfoRequest:
    del n_samples
    return wire.decode_info(payload) if payload else wire.InfoRequest()


def _decode_submap(payload: bytes, n_samples: int
                   ) -> wire.SubmapExportRequest | wire.SubmapImportRequest:
    return wire.decode_submap_request(payload, n_samples)


def _no_n(decode: Callable[[bytes], Any]) -> Callable[[bytes, int], Any]:
    def dec(payload: bytes, n_samples: int) -> Any:
        del n_samples
        return decode(payload)

    dec.__name__ = getattr(decode, "__name__", "decode")
    return dec


# --------------------------------------------------------------------------------------------
# The table
# --------------------------------------------------------------------------------------------

_TABLE = (
    Operation("update", "update", wire.UpdateRequest, wire.decode_update, wire.encode_update,
              wire.decode_ack, namespaced=True, check_namespace=_update_check,
              check_namespace_map=_update_check_map, topic="/mcsm/in/update",
              change=_update_change, retractable=True, fingerprint_parts=_update_parts,
              event_frames=lambda req, ack: (req.a, req.b),
              describe=lambda req: {"a": req.a, "b": req.b}),
    Operation("remove", "remove", wire.RemoveRequest, _no_n(wire.decode_remove),
              wire.encode_remove, wire.decode_ack, namespaced=True,
              check_namespace=_remove_check, topic="/mcsm/in/remove", change=_remove_change,
              fingerprint_parts=lambda req: [f"\0{req.frame}".encode()],
              describe=lambda req: {"frame": req.frame}),
    Operation("import", "submap", wire.SubmapImportRequest, _decode_submap,
              wire.encode_submap_import, wire.decode_ack, topic="/mcsm/in/submap_import",
              change=_import_change, fingerprint_parts=_import_parts,
              describe=lambda req: {"root": req.submap.root, "frames": list(req.submap.frames),
                                    "is_point": list(req.submap.is_point)}),
    Operation("retract", "retract", wire.RetractRequest, _no_n(wire.decode_retract),
              wire.encode_retract, wire.decode_ack, topic="/mcsm/in/retract", retract=True,
              fingerprint_parts=_target_parts, event_extra=_retract_extra,
              describe=lambda req: {"target": req.target}),
    Operation("reinstate", "reinstate", wire.RetractRequest, _no_n(wire.decode_retract),
              wire.encode_retract, wire.decode_ack, topic="/mcsm/in/reinstate", retract=False,
              fingerprint_parts=_target_parts, event_extra=_retract_extra,
              describe=lambda req: {"target": req.target}),
    Operation("relinearize", "relinearize", wire.RelinearizeRequest,
              _no_n(wire.decode_relinearize), wire.encode_relinearize, wire.decode_ack,
              topic="/mcsm/in/relinearize", change=_relinearize_change,
              fingerprint_parts=lambda req: [f"\0{req.frame}".encode()],
              event_frames=lambda req, ack: (req.frame,) if req.frame else (),
              describe=lambda req: {"frame": req.frame}),
    Operation("verdict", "verdict", wire.VerdictRequest, _no_n(wire.decode_verdict_request),
              wire.encode_verdict_request, wire.decode_ack, answer=_verdict_answer),
    Operation("query", "query", wire.QueryRequest, _no_n(wire.decode_query), wire.encode_query,
              wire.decode_query_reply, answer=_query_answer),
    Operation("info", "info", wire.InfoRequest, _decode_info, wire.encode_info,
              wire.decode_info_reply, answer=_info_answer),
    Operation("export", "submap", wire.SubmapExportRequest, _decode_submap,
              wire.encode_submap_export, wire.decode_submap_reply, answer=_export_answer),
)

OPS: Mapping[str, Operation] = {o.name: o for o in _TABLE}
"""Every operation by name."""
BY_LEAF: Mapping[str, tuple[Operation, ...]] = {
    leaf: tuple(o for o in _TABLE if o.leaf == leaf) for leaf in dict.fromkeys(
        o.leaf for o in _TABLE)}
"""The operations served on each key leaf (``submap``: export and import)."""
RECORDED: tuple[Operation, ...] = tuple(o for o in _TABLE if o.changes_state)
INPUT_TOPICS: Mapping[str, str] = {o.name: o.topic for o in RECORDED if o.topic is not None}
"""Recording topic of each state-changing operation."""
TOPIC_OPS: Mapping[str, str] = {t: name for name, t in INPUT_TOPICS.items()}


def get(name: str) -> Operation:
    """The operation called ``name``.

    Raises
    ------
    McsmError
        If there is none.
    """
    op = OPS.get(name)
    if op is None:
        raise McsmError(f"unknown operation {name!r}")
    return op


def route(keys: wire.Keys, key: str) -> tuple[str, str]:
    """``(leaf, namespace)`` of a concrete request key of the map ``keys``: ``("update",
    "robot1")`` for ``.../update/robot1``, ``("info", "")`` for ``.../info``.

    Raises
    ------
    BadMessage
        If ``key`` is not one of the map's request keys (wildcards included: a request must
        name one concrete key).
    """
    head = keys.base + "/"
    rest = key[len(head):] if key.startswith(head) else ""
    leaf, sep, ns = rest.partition("/")
    served = BY_LEAF.get(leaf)
    if served is not None:
        if not sep:
            return leaf, ""
        if served[0].namespaced and is_namespace(ns):
            return leaf, ns
    plain = [lf for lf, o in BY_LEAF.items() if not o[0].namespaced]
    spaced = [lf for lf, o in BY_LEAF.items() if o[0].namespaced]
    raise BadMessage("key", f"one of {keys.base}/{{{','.join(spaced)}}}[/<namespace>], "
                     f"{', '.join(plain)} (no wildcards)", wire.short(key))


def decode_request(leaf: str, payload: bytes, n_samples: int) -> tuple[Operation, Any]:
    """The operation and checked request of ``payload`` sent to key leaf ``leaf``.

    Raises
    ------
    McsmError
        ``BadMessage`` and the other decoder errors; an unknown leaf.
    """
    served = BY_LEAF.get(leaf)
    if served is None:
        raise McsmError(f"no operation on key leaf {leaf!r}")
    req = served[0].decode(payload, n_samples)
    for op in served:
        if isinstance(req, op.request):
            return op, req
    raise McsmError(f"no operation on {leaf!r} takes a {type(req).__name__}")


def decode_input(name: str, payload: bytes, n_samples: int) -> Any:
    """Decode a recorded state-changing request of operation ``name`` with the wire codec
    (live serving and replay share this).

    Raises
    ------
    McsmError
        If it does not decode, or decodes to another operation's request (an export cannot
        be recorded as an import).
    """
    op = get(name)
    if not op.changes_state:
        raise McsmError(f"{name!r} changes nothing and is never recorded")
    req = op.decode(payload, n_samples)
    if not isinstance(req, op.request):
        raise McsmError(f"a {type(req).__name__} cannot be recorded as {name!r}")
    return req


def fingerprint(name: str, req: Any) -> str:
    """A digest of what a state-changing request asks for (not its id or sender).

    Two requests with one id and the same fingerprint are one request sent twice (a retry);
    with different fingerprints they are different requests (``RequestIdReused``). SHA-256
    (hardware-accelerated on current CPUs) over the operation, the names and the sample
    bytes, truncated to 128 bits.

    Raises
    ------
    McsmError
        If ``name`` is not a state-changing operation or ``req`` not its request.
    """
    op = get(name)
    if op.fingerprint_parts is None or not isinstance(req, op.request):
        raise McsmError(f"no fingerprint for {type(req).__name__} as {name!r}")
    h = hashlib.sha256(name.encode())
    for part in op.fingerprint_parts(req):
        h.update(part)
    return h.hexdigest()[:32]


def event(name: str, st: MapState, req: Any, ack: wire.Ack, *, time_ns: int,
          digest: str | None) -> wire.Event:
    """The event published after ``ack``: the frames it touched and what else changed."""
    op = get(name)
    extra: dict[str, Any] = {"verdict": ack.verdict.to_dict()} if ack.verdict else {}
    if st.last_changed:  # held closures (--gate-defer) this input decided
        extra["changed"] = {rid: v.to_dict() for rid, v in st.last_changed.items()}
    if ack.relin:  # a relinearisation: what it did
        extra["relin"] = ack.relin
    extra.update(op.event_extra(st, req))
    return wire.Event(map=st.name, seq=ack.seq, op=name, kind=ack.kind,
                      frames=tuple(op.event_frames(req, ack)), component=ack.component,
                      time_ns=time_ns, digest=digest, extra=extra,
                      request_id=str(getattr(req, "request_id", "") or ""))


__all__ = ["Change", "Context", "Operation", "OPS", "BY_LEAF", "RECORDED", "INPUT_TOPICS",
           "TOPIC_OPS", "get", "route", "decode_request", "decode_input", "fingerprint",
           "event"]
