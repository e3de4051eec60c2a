"""The wire's bottom: limits, msgpack framing and the checks every decoder runs.

The protocol version and limits, :func:`pack` / :func:`unpack` (bounded msgpack), the scalar
and frame-name checks, sample arrays (``{dtype, shape, data}``: dtype, shape, the map's N,
byte length, finiteness, quaternion norm), and the machinery that encodes and decodes a
message dataclass field by field (:func:`wire_field`, :func:`message_dict`,
:func:`from_message_dict`). Everything else in :mod:`mcsm.wire` builds on this module.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, fields
from typing import Any, Literal, TypeVar, cast

import msgpack
import numpy as np
import numpy.typing as npt

from mcsm.core.at import QUAT_NORM_TOL as _CORE_QUAT_NORM_TOL
from mcsm.core.at import quaternion_problem
from mcsm.core.names import FRAME_RULE, is_frame_name
from mcsm.errors import (
    BadMessage,
    InvalidSamples,
    LimitExceeded,
    SampleCountMismatch,
    UnsupportedVersion,
)

Samples = npt.NDArray[np.float64]

VERSION = 1
"""Protocol version written in the ``v`` field of every message."""

ENCODING = "application/msgpack"
"""Zenoh encoding of every payload the server sends (replies, error replies, events)."""

MAX_PAYLOAD_BYTES = 8 * 1024 * 1024 - 64 * 1024
"""Largest request the server decodes and a client sends: 64 KiB under the server's Zenoh
``max_message_size`` (8 MiB), so an accepted payload always fits in one Zenoh message."""
MAX_REPLY_BYTES = 1024 * 1024 * 1024
"""Largest reply a client decodes (submap exports of big maps are large)."""
MAX_SAMPLES = 100_000
MAX_SUBMAP_FRAMES = 100_000
MAX_INFO_FRAMES = 10_000_000
"""Most frames (and components) an ``info`` reply may list: the reply lists every frame, and
MAX_REPLY_BYTES bounds it first (about 20 bytes a frame name, twice: frames and components)."""
MAX_ID_CHARS = 128
MAX_SENDER_CHARS = 256
QUAT_NORM_TOL = _CORE_QUAT_NORM_TOL
"""Tolerance on ``| |q|^2 - 1 |`` for every sample's quaternion (the core's, one rule)."""

F8 = np.dtype("<f8")
QueryWant = Literal["samples", "marginal"]
M = TypeVar("M")


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
           max_map_len: int = 64, max_array_len: int = MAX_SUBMAP_FRAMES) -> dict[str, Any]:
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
            max_bin_len=max_bytes, max_str_len=64 * 1024, max_array_len=max_array_len,
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
