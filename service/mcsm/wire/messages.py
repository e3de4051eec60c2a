"""The wire's messages: the request, reply and event dataclasses, checked and frozen.

Requests (:class:`UpdateRequest` ... :class:`SubmapImportRequest`) are built by their
decoders in :mod:`mcsm.wire.codec`; replies and events (:class:`Ack`, :class:`QueryReply`,
:class:`MapInfo`, :class:`SubmapReply`, :class:`Event`, :class:`Verdict`) are encoded and
decoded field by field from their ``wire_field`` metadata. A submap (one component) travels
as :class:`SubmapData` (:func:`decode_submap_data` checks one).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mcsm.errors import BadMessage, LimitExceeded, SampleCountMismatch
from mcsm.wire.checks import (
    _NAMES,
    F8,
    MAX_ID_CHARS,
    MAX_PAYLOAD_BYTES,
    MAX_REPLY_BYTES,
    MAX_SUBMAP_FRAMES,
    Check,
    QueryWant,
    Samples,
    WireField,
    _is_empty,
    _is_none,
    _keys,
    check_bool,
    check_choice,
    check_count,
    check_counts,
    check_frame,
    check_int_or_nil,
    check_map,
    check_names,
    check_number_or_nil,
    check_quaternions,
    check_str_or_nil,
    check_text,
    decode_samples,
    from_message_dict,
    message_dict,
    pack_array,
    short,
    unpack_array,
    wire_field,
)

# --------------------------------------------------------------------------------------------
# Messages
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class UpdateRequest:
    """An AT ``a -> b`` as N samples ``(N, 7)``, or a point ``b`` seen from ``a`` ``(N, 3)``."""

    request_id: str
    a: str
    b: str
    samples: Samples
    sender: str = ""
    trusted: bool = False
    """Bypass the map's loop-closure gate (the source vouches for this constraint)."""
    stamp_ns: int | None = None
    """The source's measurement time (ns since the epoch), recorded and returned in verdicts."""

    @property
    def point(self) -> bool:
        return bool(self.samples.shape[1] == 3)


@dataclass(frozen=True)
class RemoveRequest:
    request_id: str
    frame: str
    sender: str = ""


@dataclass(frozen=True)
class RetractRequest:
    """Retract (or reinstate, by the key it is sent to) the update ``target`` (a request id)."""

    request_id: str
    target: str
    sender: str = ""


@dataclass(frozen=True)
class RelinearizeRequest:
    """Relinearise ``frame``'s component, or every component when ``frame`` is empty: solve
    for the maximum a posteriori estimate of everything it has seen and redraw its samples
    (:meth:`mcsm.core.smap.StochasticMap.relinearize`)."""

    request_id: str
    frame: str = ""
    sender: str = ""


@dataclass(frozen=True)
class VerdictRequest:
    """Ask for the current verdict of the request ``target`` (a request id)."""

    request_id: str
    target: str


@dataclass(frozen=True)
class QueryRequest:
    request_id: str
    a: str
    b: str
    want: QueryWant = "samples"


@dataclass(frozen=True)
class InfoRequest:
    request_id: str = ""


@dataclass(frozen=True)
class SubmapData:
    """One component on the wire: names, point flags and edges ``(M, N, 7)`` (root first).

    ``edges[i]`` is the AT root -> ``frames[i]``; ``edges[0]`` is the identity. It converts
    to and from the core's ``Submap`` with :func:`submap_from_core` / :meth:`to_core`.
    """

    root: str
    frames: tuple[str, ...]
    is_point: tuple[bool, ...]
    edges: Samples

    def to_core(self) -> Any:
        from mcsm.core.smap import Submap  # the core is numpy-only; imported on use

        return Submap(root=self.root, frames=tuple(self.frames),
                      is_point=tuple(self.is_point), edges=self.edges)


def submap_from_core(sub: Any) -> SubmapData:
    """Wrap the core's ``Submap`` (attributes root, frames, is_point, edges) for the wire."""
    return SubmapData(root=str(sub.root), frames=tuple(str(f) for f in sub.frames),
                      is_point=tuple(bool(p) for p in sub.is_point),
                      edges=np.ascontiguousarray(sub.edges, dtype=F8))


@dataclass(frozen=True)
class SubmapExportRequest:
    request_id: str
    frame: str


@dataclass(frozen=True)
class SubmapImportRequest:
    request_id: str
    submap: SubmapData
    sender: str = ""


VERDICT_STATUSES = ("accepted", "rejected", "pending", "retracted", "reinstated")


@dataclass(frozen=True)
class Verdict:
    """What the map did with one constraint (an update): ``status`` (accepted, rejected, ...),
    the gate's ``nis`` over ``dof`` live dimensions against ``threshold`` (None: not gated),
    ``reason`` (why there was nothing to test, or "trusted"), and the source's ``stamp_ns``.
    Encoded field by field (:func:`message_dict`)."""

    status: str = field(metadata=wire_field(check_choice(VERDICT_STATUSES, 16)))
    nis: float | None = field(default=None, metadata=wire_field(check_number_or_nil))
    dof: int = field(default=0, metadata=wire_field(check_count))
    threshold: float | None = field(default=None, metadata=wire_field(check_number_or_nil))
    reason: str = field(default="", metadata=wire_field(check_text(256)))
    stamp_ns: int | None = field(default=None, metadata=wire_field(check_int_or_nil))

    def to_dict(self) -> dict[str, Any]:
        return message_dict(self)

    @classmethod
    def from_dict(cls, d: Any) -> Verdict:
        return from_message_dict(cls, d, "verdict.")


@dataclass(frozen=True)
class Ack:
    """The server's acknowledgement of an applied operation.

    ``seq`` is the map's sequence number of the operation (1, 2, ... in apply order);
    ``kind`` is the core's result kind (``new_component``, ``new_frame``, ``join``,
    ``loop_closure``, ``import``, ``remove``); ``duplicate`` is true when the request id had
    already been applied and this is the original acknowledgement, sent again; ``server`` is
    the Zenoh id of the server that applied it (``""`` from an older server).
    """

    request_id: str = field(metadata=wire_field(check_text(MAX_ID_CHARS), key="id"))
    seq: int = field(metadata=wire_field(check_count))
    op: str = field(metadata=wire_field(check_text(32)))
    kind: str = field(metadata=wire_field(check_text(32)))
    component: str | None = field(metadata=wire_field(check_str_or_nil))
    frames_added: tuple[str, ...] = field(default=(), metadata=_NAMES)
    frames_removed: tuple[str, ...] = field(default=(), metadata=_NAMES)
    duplicate: bool = field(default=False, metadata=wire_field(check_bool))
    server: str = field(default="", metadata=wire_field(check_text(MAX_ID_CHARS),
                                                        required=False))
    verdict: Verdict | None = field(default=None, metadata=wire_field(
        lambda v, name: Verdict.from_dict(v), pack=message_dict, required=False, omit=_is_none))
    relin: dict[str, Any] | None = field(default=None, metadata=wire_field(
        lambda v, name: check_map(v, name), pack=dict, required=False, omit=_is_none))


def _check_mean(val: Any, name: str) -> Samples:
    mean = unpack_array(val, name, 1, max_elems=7)
    if mean.shape != (7,):
        raise BadMessage(name, "shape (7,)", str(mean.shape))
    return mean


def _check_cov(val: Any, name: str) -> Samples:
    cov = unpack_array(val, name, 2, max_elems=36)
    if cov.shape != (6, 6):
        raise BadMessage(name, "shape (6, 6)", str(cov.shape))
    return cov


def _optional_array(check: Check) -> dict[str, WireField]:
    """An array field a reply may leave out (None: not sent)."""
    return wire_field(check, pack=lambda a: pack_array(a), required=False, omit=_is_none)


@dataclass(frozen=True)
class QueryReply:
    """What ``<prefix>/<map>/query`` answers: the samples ``(N, 7)`` of ``a -> b``, or their
    mean ``(7,)`` and tangent covariance ``(6, 6)`` (both or neither). Encoded field by field."""

    request_id: str = field(metadata=wire_field(check_text(MAX_ID_CHARS), key="id"))
    a: str = field(metadata=wire_field(lambda v, n: check_frame(v, n)))
    b: str = field(metadata=wire_field(lambda v, n: check_frame(v, n)))
    seq: int = field(metadata=wire_field(check_count))
    samples: Samples | None = field(default=None, metadata=_optional_array(
        lambda v, n: decode_samples(v, None, widths=(7,), fieldname=n)))
    mean: Samples | None = field(default=None, metadata=_optional_array(_check_mean))
    cov: Samples | None = field(default=None, metadata=_optional_array(_check_cov))

    def __post_init__(self) -> None:
        if (self.mean is None) != (self.cov is None):
            raise BadMessage("mean/cov", "both mean and cov, or neither",
                             "only " + ("mean" if self.cov is None else "cov"))


@dataclass(frozen=True)
class MapInfo:
    """What ``<prefix>/<map>/info`` answers (encoded field by field)."""

    map: str = field(metadata=wire_field(check_text(64)))
    n_samples: int = field(metadata=wire_field(check_count))
    options: dict[str, Any] = field(metadata=wire_field(check_map, pack=dict))
    seq: int = field(metadata=wire_field(check_count))
    digest: str = field(metadata=wire_field(check_text(128)))
    frames: tuple[str, ...] = field(metadata=_NAMES)
    components: dict[str, tuple[str, ...]] = field(metadata=wire_field(
        lambda v, n: {str(k): check_names(c, n) for k, c in check_map(v, n).items()},
        pack=lambda c: {k: list(v) for k, v in c.items()}))
    rejected: int = field(metadata=wire_field(check_count))
    rejected_by_error: dict[str, int] = field(metadata=wire_field(check_counts, pack=dict))
    server_id: str = field(metadata=wire_field(check_text(256)))
    recording: str = field(metadata=wire_field(check_text(4096)))
    queue_length: int = field(default=0, metadata=wire_field(check_count, required=False))
    verdicts: dict[str, int] = field(default_factory=dict, metadata=wire_field(
        check_counts, pack=dict, required=False))
    """Updates per verdict status (accepted, rejected, ...)."""
    role: str = field(default="primary", metadata=wire_field(check_text(16), required=False))
    """``primary`` (a standby has no map queryable: only the primary answers info)."""
    standbys: dict[str, int] = field(default_factory=dict, metadata=wire_field(
        check_counts, pack=dict, required=False))
    """Each standby's server id and the last seq the log delivered to it (its lag: ``seq``
    minus that), from the log's consumers (``mcsm serve --nats``)."""
    replicas: int = field(default=0, metadata=wire_field(check_count, required=False))
    """Copies of the map's log (JetStream R; 0: not replicated)."""
    epoch: int = field(default=0, metadata=wire_field(check_count, required=False))
    """The lease revision this primary took the map with: grows with every takeover (0: not
    replicated; docs/fleet.md)."""
    device: str = field(default="cpu", metadata=wire_field(check_text(64), required=False))
    """Where the map's edges live: ``cpu`` or ``cuda:K`` (``mcsm serve --device``)."""
    device_bytes: int = field(default=0, metadata=wire_field(check_count, required=False))
    """Bytes of the map's edges, flags and spare buffer where they live."""
    device_free_bytes: int = field(default=0, metadata=wire_field(check_count,
                                                                  required=False))
    """On a GPU: device memory free when the info was taken (0 on the CPU)."""

    @property
    def n_frames(self) -> int:
        return len(self.frames)


@dataclass(frozen=True)
class SubmapReply:
    """What an export on ``<prefix>/<map>/submap`` answers (encoded field by field)."""

    request_id: str = field(metadata=wire_field(check_text(MAX_ID_CHARS), key="id"))
    seq: int = field(metadata=wire_field(check_count))
    submap: SubmapData = field(metadata=wire_field(lambda v, n: decode_submap_data(v, None),
                                                   pack=lambda sub: _pack_submap(sub)))


@dataclass(frozen=True)
class Event:
    """One applied operation, as published on ``<prefix>/<map>/events`` (encoded field by
    field, :func:`message_dict`)."""

    map: str = field(metadata=wire_field(check_text(64)))
    seq: int = field(metadata=wire_field(check_count))
    op: str = field(metadata=wire_field(check_text(32)))
    kind: str = field(metadata=wire_field(check_text(32)))
    frames: tuple[str, ...] = field(metadata=_NAMES)
    component: str | None = field(metadata=wire_field(check_str_or_nil))
    time_ns: int = field(metadata=wire_field(check_count))
    digest: str | None = field(default=None, metadata=wire_field(check_str_or_nil))
    extra: dict[str, Any] = field(default_factory=dict, metadata=wire_field(
        check_map, pack=dict, required=False, omit=_is_empty))
    request_id: str = field(default="", metadata=wire_field(
        check_text(MAX_ID_CHARS), key="id", required=False, omit=_is_empty))
    """The applied request's id (what ``retract``, ``reinstate`` and ``verdict`` take)."""



def _pack_submap(sub: SubmapData) -> dict[str, Any]:
    return {"root": sub.root, "frames": list(sub.frames), "is_point": list(sub.is_point),
            "edges": pack_array(sub.edges)}


def decode_submap_data(obj: Any, n_samples: int | None) -> SubmapData:
    """Check a submap map: unique valid names, flags, edges ``(M, N, 7)``, unit quaternions."""
    if not isinstance(obj, dict):
        raise BadMessage("submap", "a map {root, frames, is_point, edges}", type(obj).__name__)
    _keys(obj, ("root", "frames", "is_point", "edges"))
    root = check_frame(obj["root"], "submap.root")
    frames = obj["frames"]
    flags = obj["is_point"]
    if not isinstance(frames, list) or not frames:
        raise BadMessage("submap.frames", "a non-empty list of frame names", short(frames))
    if len(frames) > MAX_SUBMAP_FRAMES:
        raise LimitExceeded("submap frames", len(frames), MAX_SUBMAP_FRAMES)
    for f in frames:
        check_frame(f, "submap.frames")
    if len(set(frames)) != len(frames):
        raise BadMessage("submap.frames", "unique names", "duplicates")
    if frames[0] != root:
        raise BadMessage("submap.frames", "the root first", short(frames[0]))
    if (not isinstance(flags, list) or len(flags) != len(frames)
            or not all(isinstance(p, bool) for p in flags)):
        raise BadMessage("submap.is_point", f"a list of {len(frames)} booleans", short(flags))
    e = obj["edges"]
    if isinstance(e, dict) and isinstance(e.get("shape"), list) and len(e["shape"]) == 3:
        m, n, w = e["shape"]
        if type(n) is int and n_samples is not None and n != n_samples:
            raise SampleCountMismatch(n_samples, n)
        if m != len(frames) or w != 7:
            raise BadMessage("submap.edges.shape", f"({len(frames)}, N, 7)", short(e["shape"]))
    edges = unpack_array(e, "submap.edges", 3,
                         max_elems=MAX_PAYLOAD_BYTES // 8 if n_samples is not None
                         else MAX_REPLY_BYTES // 8)
    if edges.shape[0] != len(frames) or edges.shape[2] != 7 or edges.shape[1] == 0:
        raise BadMessage("submap.edges.shape", f"({len(frames)}, N, 7)", list(edges.shape))
    check_quaternions(edges[..., 3:7], "submap.edges")
    return SubmapData(root=root, frames=tuple(frames), is_point=tuple(flags), edges=edges)

