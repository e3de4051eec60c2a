"""The wire contract: msgpack payloads <-> checked, frozen dataclasses.

This module is the only place where bytes become arrays. Every decoder checks, in order: the
payload length before unpacking (and msgpack's ``max_*_len`` limits), that the top level is a
map, the version field, the set of keys, the types of scalar fields, frame names, and sample
arrays (dtype, shape, the map's N, byte length, finiteness, quaternion norm). A decoder returns
a frozen dataclass or raises an :class:`mcsm.errors.McsmError` subclass; it never returns a
half-checked value. The JSON Schemas in ``schemas/`` describe the same messages (binary fields
shown as base64 strings, Foxglove's convention for JSON views).

Arrays travel as ``{"dtype": "<f8", "shape": [...], "data": <raw little-endian bytes>}``,
never pickle or numpy's own format. Sample columns are ``x y z qw qx qy qz`` (scalar-first
quaternion, PAPER §1); point observations are ``(N, 3)`` ``x y z``.

The server and the clients both import this module, so what one side encodes the other side
decodes with the very same code. Replay decodes recorded requests through it too.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, fields
from typing import Any, Literal, TypeVar, cast

import msgpack
import numpy as np
import numpy.typing as npt

from mcsm.core.at import QUAT_NORM_TOL as _CORE_QUAT_NORM_TOL
from mcsm.core.at import quaternion_problem
from mcsm.core.names import FRAME_RULE, NAMESPACE_RULE, is_frame_name, is_namespace
from mcsm.errors import (
    BadMessage,
    InvalidSamples,
    LimitExceeded,
    McsmError,
    SampleCountMismatch,
    UnsupportedVersion,
)

Samples = npt.NDArray[np.float64]

VERSION = 1
"""Protocol version written in the ``v`` field of every message."""

ENCODING = "application/msgpack"
"""Zenoh encoding of every payload the server sends (replies, error replies, events)."""

DEFAULT_PREFIX = "mcsm"
DEFAULT_MAP = "default"

MAX_PAYLOAD_BYTES = 8 * 1024 * 1024 - 64 * 1024
"""Largest request the server decodes and a client sends: 64 KiB under the server's Zenoh
``max_message_size`` (8 MiB), so an accepted payload always fits in one Zenoh message."""
MAX_REPLY_BYTES = 1024 * 1024 * 1024
"""Largest reply a client decodes (submap exports of big maps are large)."""
MAX_SAMPLES = 100_000
MAX_SUBMAP_FRAMES = 100_000
MAX_ID_CHARS = 128
MAX_SENDER_CHARS = 256
QUAT_NORM_TOL = _CORE_QUAT_NORM_TOL
"""Tolerance on ``| |q|^2 - 1 |`` for every sample's quaternion (the core's, one rule)."""

F8 = np.dtype("<f8")
_MAP_RE = re.compile(r"[A-Za-z0-9_.+-]{1,64}")
_PREFIX_RE = re.compile(r"[A-Za-z0-9_.+-]{1,64}(/[A-Za-z0-9_.+-]{1,64}){0,7}")

QueryWant = Literal["samples", "marginal"]
M = TypeVar("M")


# --------------------------------------------------------------------------------------------
# Key expressions
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Keys:
    """The key expressions of one map (``<prefix>/<map>/...``); see ``schemas/KEYS.md``.

    ``update`` and ``remove`` write any frame; ``update_as(ns)`` and ``remove_as(ns)``
    (``.../update/<ns>``) write only frames of namespace ``ns``: the shipped access-control
    lists grant a robot's identity its own namespace's keys alone (``deploy/``).
    """

    prefix: str
    map: str

    def _k(self, leaf: str) -> str:
        return f"{self.prefix}/{self.map}/{leaf}"

    @property
    def base(self) -> str:
        """``<prefix>/<map>``: every key of the map is under it."""
        return f"{self.prefix}/{self.map}"

    @property
    def all(self) -> str:
        """``<prefix>/<map>/**``: the server's one queryable (one arrival order per map)."""
        return self._k("**")

    @property
    def update(self) -> str:
        return self._k("update")

    @property
    def remove(self) -> str:
        return self._k("remove")

    def update_as(self, namespace: str) -> str:
        """Update key restricted to frames ``a`` in ``namespace`` (checked by the server)."""
        return self._k(f"update/{check_namespace(namespace)}")

    def remove_as(self, namespace: str) -> str:
        """Remove key restricted to frames in ``namespace`` (checked by the server)."""
        return self._k(f"remove/{check_namespace(namespace)}")

    @property
    def query(self) -> str:
        return self._k("query")

    @property
    def info(self) -> str:
        return self._k("info")

    @property
    def submap(self) -> str:
        return self._k("submap")

    @property
    def retract(self) -> str:
        return self._k("retract")

    @property
    def reinstate(self) -> str:
        return self._k("reinstate")

    @property
    def verdict(self) -> str:
        return self._k("verdict")

    @property
    def relinearize(self) -> str:
        return self._k("relinearize")

    @property
    def events(self) -> str:
        return self._k("events")

    def alive(self, server_id: str) -> str:
        """Liveliness token of one live server serving this map."""
        return self._k(f"alive/{server_id}")

    @property
    def alive_any(self) -> str:
        return self._k("alive/*")

    def request(self, leaf: str, namespace: str = "") -> str:
        """The request key of operation leaf ``leaf`` (see :mod:`mcsm.ops`), restricted to
        ``namespace`` if given (``.../update/robot1``)."""
        return self._k(f"{leaf}/{check_namespace(namespace)}" if namespace else leaf)

    # No replication keys: standbys follow the map's log in NATS JetStream
    # (:mod:`mcsm.replication`), never through Zenoh.

    def route(self, key: str) -> tuple[str, str]:
        """``(leaf, namespace)`` of a concrete request key of this map (:func:`mcsm.ops.route`).

        Raises
        ------
        BadMessage
            If ``key`` is not one of the map's request keys (wildcards included).
        """
        from mcsm import ops  # the table of operations builds on this module

        return ops.route(self, key)


def check_namespace(namespace: str) -> str:
    """Return ``namespace`` if it is a valid frame-name segment (``robot1``), else raise."""
    if not is_namespace(namespace):
        raise BadMessage("namespace", NAMESPACE_RULE,
                         short(namespace))
    return namespace


def map_keys(map_name: str = DEFAULT_MAP, prefix: str = DEFAULT_PREFIX) -> Keys:
    """Key expressions of map ``map_name`` under ``prefix``; checks both names.

    Raises
    ------
    BadMessage
        If the map name is not 1-64 characters from ``[A-Za-z0-9_.+-]`` or the prefix is not
        1-8 such segments joined by ``/``.
    """
    if not isinstance(map_name, str) or not _MAP_RE.fullmatch(map_name):
        raise BadMessage("map", "a map name of 1-64 characters from [A-Za-z0-9_.+-]",
                         short(map_name))
    if not isinstance(prefix, str) or not _PREFIX_RE.fullmatch(prefix):
        raise BadMessage("prefix", "1-8 segments of [A-Za-z0-9_.+-] joined by '/'",
                         short(prefix))
    return Keys(prefix=prefix, map=map_name)


# --------------------------------------------------------------------------------------------
# Messages derived from their dataclasses
# --------------------------------------------------------------------------------------------
# A reply or event dataclass whose every field carries ``metadata=wire_field(...)`` is encoded
# and decoded field by field (:func:`message_dict`, :func:`from_message_dict`): adding a field
# to such a message is one edit here plus its JSON Schema. Each field names its wire key, the
# check its decoded value must pass (the hostile-input rules: types, lengths, ranges), how it
# is packed, whether a peer may omit it (a field added later: older peers do not send it, the
# dataclass default applies) and whether the encoder leaves it out (e.g. when None).

Check = Callable[[Any, str], Any]


@dataclass(frozen=True)
class WireField:
    """How one dataclass field travels: see :func:`wire_field`."""

    key: str | None
    check: Check
    pack: Callable[[Any], Any]
    required: bool
    omit: Callable[[Any], bool] | None


def wire_field(check: Check, *, key: str | None = None, pack: Callable[[Any], Any] | None = None,
               required: bool = True, omit: Callable[[Any], bool] | None = None
               ) -> dict[str, WireField]:
    """Field metadata: ``check(value, fieldname)`` returns the checked Python value or raises
    ``BadMessage``/``LimitExceeded``; ``key`` is the wire name (default: the field's);
    ``pack`` turns the value into msgpack types (default: as is); ``required=False`` lets a
    peer leave it out (the field's default applies); ``omit(value)`` true leaves it out."""
    return {"wire": WireField(key, check, pack if pack is not None else _same, required, omit)}


def _same(x: Any) -> Any:
    return x


def _wire_fields(cls: type) -> list[tuple[str, str, WireField]]:
    """``(attribute, wire key, spec)`` of every field of a derived message dataclass."""
    out = []
    for f in fields(cls):
        spec = f.metadata.get("wire")
        if not isinstance(spec, WireField):
            raise TypeError(f"{cls.__name__}.{f.name} has no wire_field metadata")
        out.append((f.name, spec.key or f.name, spec))
    return out


def message_dict(obj: Any) -> dict[str, Any]:
    """The wire map of a derived message (without ``v``)."""
    d: dict[str, Any] = {}
    for name, key, spec in _wire_fields(type(obj)):
        val = getattr(obj, name)
        if spec.omit is not None and spec.omit(val):
            continue
        d[key] = spec.pack(val)
    return d


def from_message_dict(cls: type[M], d: Any, where: str = "") -> M:
    """Check a decoded wire map field by field and build ``cls`` (``where`` prefixes the
    field names in errors, e.g. ``"verdict."``).

    Raises
    ------
    BadMessage, LimitExceeded
        A missing required or unknown key, or a value that fails its field's check.
    """
    if not isinstance(d, dict):
        raise BadMessage(where.rstrip(".") or "payload", "a map", type(d).__name__)
    specs = _wire_fields(cls)
    _keys(d, [key for _, key, spec in specs if spec.required],
          [key for _, key, spec in specs if not spec.required], prefix=where)
    return cls(**{name: spec.check(d[key], where + key)
                  for name, key, spec in specs if key in d})


def check_text(max_chars: int, min_chars: int = 0) -> Check:
    """A check: a string of ``min_chars`` to ``max_chars`` characters."""
    def check(val: Any, name: str) -> str:
        return check_str(val, name, max_chars=max_chars, min_chars=min_chars)
    return check


def check_choice(choices: tuple[str, ...], max_chars: int = 32) -> Check:
    """A check: one of ``choices``."""
    def check(val: Any, name: str) -> str:
        text = check_str(val, name, max_chars=max_chars)
        if text not in choices:
            raise BadMessage(name, " | ".join(choices), short(text))
        return text
    return check


def check_count(val: Any, name: str) -> int:
    """A check: an integer >= 0 (not a bool)."""
    if type(val) is not int or val < 0:
        raise BadMessage(name, "an integer >= 0", short(val))
    return val


def check_bool(val: Any, name: str) -> bool:
    if type(val) is not bool:
        raise BadMessage(name, "true or false", short(val))
    return val


def check_str_or_nil(val: Any, name: str) -> str | None:
    if val is not None and not isinstance(val, str):
        raise BadMessage(name, "a string or nil", short(val))
    return val


def check_int_or_nil(val: Any, name: str) -> int | None:
    if val is not None and type(val) is not int:
        raise BadMessage(name, "an integer or nil", short(val))
    return val


def check_number_or_nil(val: Any, name: str) -> float | None:
    if val is not None and (isinstance(val, bool) or not isinstance(val, (int, float))):
        raise BadMessage(name, "a number or nil", short(val))
    return None if val is None else float(val)


def check_names(val: Any, name: str) -> tuple[str, ...]:
    """A check: a list of strings (returned as a tuple)."""
    if not isinstance(val, list) or not all(isinstance(s, str) for s in val):
        raise BadMessage(name, "a list of strings", short(val))
    return tuple(val)


def check_map(val: Any, name: str) -> dict[str, Any]:
    if not isinstance(val, dict):
        raise BadMessage(name, "a map", type(val).__name__)
    return val


def check_counts(val: Any, name: str) -> dict[str, int]:
    """A check: a map of names to counts (integers, not bools)."""
    if not isinstance(val, dict) or not all(
            isinstance(k, str) and type(v) is int for k, v in val.items()):
        raise BadMessage(name, "a map of names to counts", short(val))
    return dict(val)


def _is_none(x: Any) -> bool:
    return x is None


def _is_empty(x: Any) -> bool:
    return not x


_NAMES = wire_field(check_names, pack=list)


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


# --------------------------------------------------------------------------------------------
# Low-level helpers
# --------------------------------------------------------------------------------------------

def short(x: Any, n: int = 48) -> str:
    """``repr(x)``, cut to ``n`` characters (for error messages about hostile input)."""
    s = repr(x)
    return s if len(s) <= n else s[: n - 3] + "..."


def pack(obj: Mapping[str, Any]) -> bytes:
    """msgpack-encode a message map (adds nothing; callers put ``v`` in)."""
    return cast(bytes, msgpack.packb(obj, use_bin_type=True))


def unpack(payload: bytes | bytearray | memoryview, *, max_bytes: int = MAX_PAYLOAD_BYTES,
           max_map_len: int = 64) -> dict[str, Any]:
    """Bounded msgpack decode of one message map; checks the version.

    Raises
    ------
    LimitExceeded
        If the payload is longer than ``max_bytes``.
    BadMessage
        If it is not one complete msgpack map with string keys.
    UnsupportedVersion
        If ``v`` is not :data:`VERSION`.
    """
    if not isinstance(payload, (bytes, bytearray, memoryview)):
        raise BadMessage("payload", "bytes", type(payload).__name__)
    n = len(payload)
    if n > max_bytes:
        raise LimitExceeded("payload bytes", n, max_bytes)
    if n == 0:
        raise BadMessage("payload", "a msgpack map", "0 bytes")
    try:
        obj = msgpack.unpackb(
            payload, raw=False, strict_map_key=True, use_list=True,
            max_bin_len=max_bytes, max_str_len=64 * 1024, max_array_len=MAX_SUBMAP_FRAMES,
            max_map_len=max_map_len, max_ext_len=0,
        )
    except (ValueError, TypeError, OverflowError, msgpack.UnpackException) as exc:
        # ExtraData, FormatError, StackError, "incomplete input", bad UTF-8 are ValueErrors
        raise BadMessage("payload", "one msgpack map", f"undecodable ({type(exc).__name__})",
                         ) from None
    if not isinstance(obj, dict):
        raise BadMessage("payload", "a msgpack map", type(obj).__name__)
    check_version(obj)
    return obj


def check_version(obj: Mapping[str, Any]) -> None:
    """Refuse a message without ``v`` or with a version other than :data:`VERSION`."""
    if "v" not in obj:
        raise BadMessage("v", f"the protocol version {VERSION}", "missing")
    v = obj["v"]
    if type(v) is not int or v != VERSION:
        raise UnsupportedVersion(v, VERSION)


def _keys(obj: Mapping[str, Any], required: Sequence[str], optional: Sequence[str] = (), *,
          prefix: str = "") -> None:
    for k in required:
        if k not in obj:
            raise BadMessage(prefix + k, "a required field", "missing")
    allowed = set(required) | set(optional) | {"v"}
    for k in obj:
        if k not in allowed:
            raise BadMessage(prefix + str(k)[:40], "no unknown fields", "an unknown field")


def check_str(val: Any, name: str, *, max_chars: int, min_chars: int = 0) -> str:
    """``val`` if it is a string of ``min_chars`` to ``max_chars`` characters, else raise."""
    if not isinstance(val, str):
        raise BadMessage(name, "a string", type(val).__name__)
    if len(val) > max_chars:
        raise LimitExceeded(f"{name} length", len(val), max_chars)
    if len(val) < min_chars:
        raise BadMessage(name, f"at least {min_chars} characters", len(val))
    return val


def _str(obj: Mapping[str, Any], key: str, *, max_chars: int, default: str | None = None,
         min_chars: int = 0) -> str:
    if key not in obj and default is not None:
        return default
    return check_str(obj.get(key), key, max_chars=max_chars, min_chars=min_chars)


def _int(obj: Mapping[str, Any], key: str, *, lo: int = 0) -> int:
    val = obj.get(key)
    if type(val) is not int or val < lo:
        raise BadMessage(key, f"an integer >= {lo}", short(val))
    return int(val)


def check_frame(name: Any, fieldname: str = "frame") -> str:
    """Return ``name`` if it is a valid frame name, else raise :class:`BadMessage`."""
    if not is_frame_name(name):
        raise BadMessage(fieldname, FRAME_RULE, short(name))
    return name


def _request_id(obj: Mapping[str, Any]) -> str:
    return _str(obj, "id", max_chars=MAX_ID_CHARS, min_chars=1)


# --------------------------------------------------------------------------------------------
# Arrays
# --------------------------------------------------------------------------------------------

def pack_array(a: npt.ArrayLike) -> dict[str, Any]:
    """An array as ``{"dtype": "<f8", "shape": [...], "data": bytes}`` (little-endian f8)."""
    arr = np.ascontiguousarray(a, dtype=F8)
    return {"dtype": "<f8", "shape": list(arr.shape), "data": arr.tobytes()}


def unpack_array(obj: Any, fieldname: str, ndim: int, *, max_elems: int) -> Samples:
    """Check an array map and return a new writable float64 array (finiteness checked)."""
    if not isinstance(obj, dict):
        raise BadMessage(fieldname, "an array map {dtype, shape, data}", type(obj).__name__)
    if set(obj) != {"dtype", "shape", "data"}:
        raise BadMessage(fieldname, "exactly the keys dtype, shape, data",
                         sorted(str(k) for k in obj))
    if obj["dtype"] != "<f8":
        raise BadMessage(f"{fieldname}.dtype", "'<f8' (little-endian float64)",
                         short(obj["dtype"]))
    shape = obj["shape"]
    if (not isinstance(shape, list) or len(shape) != ndim
            or not all(type(s) is int and s >= 0 for s in shape)):
        raise BadMessage(f"{fieldname}.shape", f"a list of {ndim} non-negative integers",
                         short(shape))
    n_elems = math.prod(shape)
    if n_elems > max_elems:
        raise LimitExceeded(f"{fieldname} elements", n_elems, max_elems)
    data = obj["data"]
    if not isinstance(data, bytes):
        raise BadMessage(f"{fieldname}.data", "binary (msgpack bin)", type(data).__name__)
    if len(data) != 8 * n_elems:
        raise BadMessage(f"{fieldname}.data", f"{8 * n_elems} bytes for shape {shape}",
                         f"{len(data)} bytes")
    arr = np.frombuffer(data, dtype=F8).reshape(shape).copy()
    if not np.isfinite(arr).all():
        raise InvalidSamples(f"{fieldname} holds non-finite values (NaN or inf)")
    return arr


def check_quaternions(q: Samples, fieldname: str = "samples") -> None:
    """Every quaternion ``q[..., 0:4]`` must satisfy ``| |q|^2 - 1 | <= QUAT_NORM_TOL``."""
    norm2 = np.einsum("...i,...i->...", q, q)
    err = np.abs(norm2 - 1.0)
    if err.size and float(err.max()) > QUAT_NORM_TOL:
        idx = np.unravel_index(int(np.argmax(err)), err.shape)
        where = ", ".join(str(int(i)) for i in idx)
        raise InvalidSamples(f"{fieldname}: the quaternion of sample {where} "
                             f"{quaternion_problem(float(norm2[idx]))}")


def decode_samples(obj: Any, n_samples: int | None, widths: tuple[int, ...] = (7, 3),
                   fieldname: str = "samples") -> Samples:
    """Check a sample-set array map: shape ``(N, w)``, N the map's, finite, unit quaternions."""
    if isinstance(obj, dict) and isinstance(obj.get("shape"), list) and len(obj["shape"]) == 2:
        n, w = obj["shape"]
        if type(w) is int and w not in widths:
            raise BadMessage(f"{fieldname}.shape", f"(N, {' or '.join(map(str, widths))})",
                             short(obj["shape"]))
        if type(n) is int and n > MAX_SAMPLES:
            raise LimitExceeded("samples", n, MAX_SAMPLES)
        if type(n) is int and n_samples is not None and n != n_samples:
            raise SampleCountMismatch(n_samples, n)
        if type(n) is int and n == 0:
            raise BadMessage(f"{fieldname}.shape", "at least one sample", 0)
    arr = unpack_array(obj, fieldname, 2, max_elems=MAX_SAMPLES * 7)
    if arr.shape[1] == 7:
        check_quaternions(arr[:, 3:7], fieldname)
    return arr


# --------------------------------------------------------------------------------------------
# Requests: encode (clients) and decode (server, replay)
# --------------------------------------------------------------------------------------------

def encode_update(request_id: str, a: str, b: str, samples: npt.ArrayLike,
                  sender: str = "", *, trusted: bool = False,
                  stamp_ns: int | None = None) -> bytes:
    """An update request: AT ``a -> b`` ``(N, 7)`` or point ``b`` from ``a`` ``(N, 3)``;
    ``trusted`` bypasses the gate, ``stamp_ns`` is the source's measurement time."""
    d: dict[str, Any] = {"v": VERSION, "id": request_id, "a": a, "b": b,
                         "samples": pack_array(samples)}
    if sender:
        d["sender"] = sender
    if trusted:
        d["trusted"] = True
    if stamp_ns is not None:
        d["stamp_ns"] = int(stamp_ns)
    return pack(d)


def decode_update(payload: bytes, n_samples: int | None, *,
                  max_bytes: int = MAX_PAYLOAD_BYTES) -> UpdateRequest:
    """Decode and check an update request for a map of ``n_samples`` samples.

    Raises
    ------
    LimitExceeded, BadMessage, UnsupportedVersion, SampleCountMismatch, InvalidSamples
    """
    d = unpack(payload, max_bytes=max_bytes)
    _keys(d, ("id", "a", "b", "samples"), ("sender", "trusted", "stamp_ns"))
    rid = _request_id(d)
    a = check_frame(d["a"], "a")
    b = check_frame(d["b"], "b")
    sender = _str(d, "sender", max_chars=MAX_SENDER_CHARS, default="")
    trusted = d.get("trusted", False)
    if type(trusted) is not bool:
        raise BadMessage("trusted", "true or false", short(trusted))
    stamp_ns = _int(d, "stamp_ns") if "stamp_ns" in d else None
    if stamp_ns is not None and stamp_ns >= 2**63:
        raise BadMessage("stamp_ns", "an integer below 2**63", short(stamp_ns))
    samples = decode_samples(d["samples"], n_samples)
    return UpdateRequest(request_id=rid, a=a, b=b, samples=samples, sender=sender,
                         trusted=trusted, stamp_ns=stamp_ns)


def encode_remove(request_id: str, frame: str, sender: str = "") -> bytes:
    d: dict[str, Any] = {"v": VERSION, "id": request_id, "frame": frame}
    if sender:
        d["sender"] = sender
    return pack(d)


def decode_remove(payload: bytes, *, max_bytes: int = MAX_PAYLOAD_BYTES) -> RemoveRequest:
    d = unpack(payload, max_bytes=max_bytes)
    _keys(d, ("id", "frame"), ("sender",))
    return RemoveRequest(request_id=_request_id(d), frame=check_frame(d["frame"]),
                         sender=_str(d, "sender", max_chars=MAX_SENDER_CHARS, default=""))


def encode_retract(request_id: str, target: str, sender: str = "") -> bytes:
    """A retract or reinstate request (the key says which) of the update ``target``."""
    d: dict[str, Any] = {"v": VERSION, "id": request_id, "target": target}
    if sender:
        d["sender"] = sender
    return pack(d)


def decode_retract(payload: bytes, *, max_bytes: int = MAX_PAYLOAD_BYTES) -> RetractRequest:
    d = unpack(payload, max_bytes=max_bytes)
    _keys(d, ("id", "target"), ("sender",))
    return RetractRequest(request_id=_request_id(d),
                          target=_str(d, "target", max_chars=MAX_ID_CHARS),
                          sender=_str(d, "sender", max_chars=MAX_SENDER_CHARS, default=""))


def encode_relinearize(request_id: str, frame: str = "", sender: str = "") -> bytes:
    """A relinearise request of ``frame``'s component (empty: every component)."""
    d: dict[str, Any] = {"v": VERSION, "id": request_id}
    if frame:
        d["frame"] = frame
    if sender:
        d["sender"] = sender
    return pack(d)


def decode_relinearize(payload: bytes, *, max_bytes: int = MAX_PAYLOAD_BYTES
                       ) -> RelinearizeRequest:
    d = unpack(payload, max_bytes=max_bytes)
    _keys(d, ("id",), ("frame", "sender"))
    frame = check_frame(d["frame"]) if "frame" in d else ""
    return RelinearizeRequest(request_id=_request_id(d), frame=frame,
                              sender=_str(d, "sender", max_chars=MAX_SENDER_CHARS, default=""))


def encode_verdict_request(request_id: str, target: str) -> bytes:
    return pack({"v": VERSION, "id": request_id, "target": target})


def decode_verdict_request(payload: bytes, *,
                           max_bytes: int = MAX_PAYLOAD_BYTES) -> VerdictRequest:
    d = unpack(payload, max_bytes=max_bytes)
    _keys(d, ("id", "target"), ())
    return VerdictRequest(request_id=_request_id(d),
                          target=_str(d, "target", max_chars=MAX_ID_CHARS))


def encode_query(request_id: str, a: str, b: str, want: QueryWant = "samples") -> bytes:
    return pack({"v": VERSION, "id": request_id, "a": a, "b": b, "want": want})


def decode_query(payload: bytes, *, max_bytes: int = MAX_PAYLOAD_BYTES) -> QueryRequest:
    d = unpack(payload, max_bytes=max_bytes)
    _keys(d, ("id", "a", "b"), ("want",))
    want = d.get("want", "samples")
    if want not in ("samples", "marginal"):
        raise BadMessage("want", "'samples' or 'marginal'", short(want))
    return QueryRequest(request_id=_request_id(d), a=check_frame(d["a"], "a"),
                        b=check_frame(d["b"], "b"), want=want)


def encode_info(request_id: str = "") -> bytes:
    d: dict[str, Any] = {"v": VERSION}
    if request_id:
        d["id"] = request_id
    return pack(d)


def decode_info(payload: bytes, *, max_bytes: int = MAX_PAYLOAD_BYTES) -> InfoRequest:
    d = unpack(payload, max_bytes=max_bytes)
    _keys(d, (), ("id",))
    return InfoRequest(request_id=_str(d, "id", max_chars=MAX_ID_CHARS, default=""))


def encode_submap_export(request_id: str, frame: str) -> bytes:
    return pack({"v": VERSION, "id": request_id, "op": "export", "frame": frame})


def _pack_submap(sub: SubmapData) -> dict[str, Any]:
    return {"root": sub.root, "frames": list(sub.frames), "is_point": list(sub.is_point),
            "edges": pack_array(sub.edges)}


def encode_submap_import(request_id: str, submap: SubmapData | Any, sender: str = "") -> bytes:
    """An import request; ``submap`` is a :class:`SubmapData` or the core's ``Submap``."""
    sub = submap if isinstance(submap, SubmapData) else submap_from_core(submap)
    d: dict[str, Any] = {"v": VERSION, "id": request_id, "op": "import",
                         "submap": _pack_submap(sub)}
    if sender:
        d["sender"] = sender
    return pack(d)


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


def decode_submap_request(payload: bytes, n_samples: int | None, *,
                          max_bytes: int = MAX_PAYLOAD_BYTES,
                          ) -> SubmapExportRequest | SubmapImportRequest:
    """Decode a request on ``<prefix>/<map>/submap``: ``op`` is ``export`` or ``import``."""
    d = unpack(payload, max_bytes=max_bytes)
    op = d.get("op")
    if op == "export":
        _keys(d, ("id", "op", "frame"))
        return SubmapExportRequest(request_id=_request_id(d), frame=check_frame(d["frame"]))
    if op == "import":
        _keys(d, ("id", "op", "submap"), ("sender",))
        rid = _request_id(d)
        sender = _str(d, "sender", max_chars=MAX_SENDER_CHARS, default="")
        return SubmapImportRequest(request_id=rid, submap=decode_submap_data(d["submap"],
                                                                              n_samples),
                                   sender=sender)
    raise BadMessage("op", "'export' or 'import'", short(op))


# --------------------------------------------------------------------------------------------
# Replies: encode (server) and decode (clients)
# --------------------------------------------------------------------------------------------

def encode_ack(ack: Ack) -> bytes:
    return pack({"v": VERSION, **message_dict(ack)})


def decode_ack(payload: bytes) -> Ack:
    return from_message_dict(Ack, unpack(payload, max_bytes=MAX_REPLY_BYTES))


def encode_query_reply(r: QueryReply) -> bytes:
    return pack({"v": VERSION, **message_dict(r)})


def decode_query_reply(payload: bytes) -> QueryReply:
    return from_message_dict(QueryReply, unpack(payload, max_bytes=MAX_REPLY_BYTES))


def encode_info_reply(info: MapInfo) -> bytes:
    return pack({"v": VERSION, **message_dict(info)})


def decode_info_reply(payload: bytes) -> MapInfo:
    # one entry per component: allow as many as a map may have frames
    return from_message_dict(MapInfo, unpack(payload, max_bytes=MAX_REPLY_BYTES,
                                             max_map_len=MAX_SUBMAP_FRAMES))


def encode_submap_reply(r: SubmapReply) -> bytes:
    return pack({"v": VERSION, **message_dict(r)})


def decode_submap_reply(payload: bytes) -> SubmapReply:
    return from_message_dict(SubmapReply, unpack(payload, max_bytes=MAX_REPLY_BYTES))


def encode_error(err: McsmError, request_id: str = "") -> bytes:
    """An error reply: ``McsmError.to_dict()`` plus ``v`` and the request id if known."""
    d: dict[str, Any] = {"v": VERSION, **err.to_dict()}
    if request_id:
        d["id"] = request_id
    return pack(d)


def decode_error(payload: bytes) -> McsmError:
    """Rebuild the typed error of an error reply (``McsmError.from_dict``).

    Raises
    ------
    BadMessage
        If the payload is not an mcsm error reply (e.g. Zenoh's own ``Timeout`` text).
    """
    d = unpack(payload, max_bytes=MAX_PAYLOAD_BYTES)
    _keys(d, ("error", "message"), ("fields", "id"))
    if not isinstance(d["error"], str) or not isinstance(d["message"], str):
        raise BadMessage("error", "strings error and message", short(d))
    if "fields" in d and not isinstance(d["fields"], dict):
        raise BadMessage("fields", "a map", type(d["fields"]).__name__)
    return McsmError.from_dict(d)


def encode_event(ev: Event) -> bytes:
    return pack({"v": VERSION, **message_dict(ev)})


def decode_event(payload: bytes) -> Event:
    return from_message_dict(Event, unpack(payload, max_bytes=MAX_PAYLOAD_BYTES))
