"""One table of malformed requests, shared by the codec tests and the over-Zenoh server tests.

Each case is ``(id, op, build, error)``: ``build(n_samples)`` returns the raw payload sent to
``<prefix>/<map>/<op>``, and ``error`` is the ``McsmError`` subclass name the server (or the
decoder) must answer with. Cases marked ``map_level`` pass the codec and are refused by the map
(they need frames ``w`` and ``r`` already in the map, and ``lonely`` in another component).
"""

from __future__ import annotations

from collections.abc import Callable

import msgpack
import numpy as np
from mcsm import ops, wire
from mcsm.core.at import identity


def good_samples(n: int, width: int = 7) -> np.ndarray:
    if width == 3:
        return np.tile([1.0, 2.0, 3.0], (n, 1))
    x = identity(n)
    x[:, 0] = np.linspace(0.5, 1.5, n)
    return x


def arr_map(a: np.ndarray, dtype: str = "<f8", shape: list[int] | None = None,
            data: bytes | None = None) -> dict:
    return {"dtype": dtype, "shape": list(a.shape) if shape is None else shape,
            "data": np.ascontiguousarray(a, dtype="<f8").tobytes() if data is None else data}


def update_dict(n: int, a: str = "w", b: str = "r", samples: dict | None = None, **extra) -> dict:
    d = {"v": 1, "id": "bad-1", "a": a, "b": b,
         "samples": arr_map(good_samples(n)) if samples is None else samples}
    d.update(extra)
    return d


def pk(d: object) -> bytes:
    return msgpack.packb(d, use_bin_type=True)


def _with(n: int, fn: Callable[[np.ndarray], None]) -> bytes:
    x = good_samples(n)
    fn(x)
    return pk(update_dict(n, samples=arr_map(x)))


def _nan(x: np.ndarray) -> None:
    x[3, 1] = np.nan


def _inf(x: np.ndarray) -> None:
    x[0, 0] = np.inf


def _zero_q(x: np.ndarray) -> None:
    x[5, 3:7] = 0.0


def _long_q(x: np.ndarray) -> None:
    x[2, 3:7] = [1.001, 0.0, 0.0, 0.0]


def _minus(d: dict, key: str) -> dict:
    d = dict(d)
    del d[key]
    return d


# (id, op, build(n) -> payload, expected error name, map_level)
CASES: list[tuple[str, str, Callable[[int], bytes], str, bool]] = [
    ("garbage-bytes", "update", lambda n: b"\xc1\xff\x00garbage\x93", "BadMessage", False),
    ("empty-payload", "update", lambda n: b"", "BadMessage", False),
    ("truncated-msgpack", "update", lambda n: pk(update_dict(n))[:-10], "BadMessage", False),
    ("trailing-bytes", "update", lambda n: pk(update_dict(n)) + b"\x00", "BadMessage", False),
    ("top-level-list", "update", lambda n: pk([1, 2, 3]), "BadMessage", False),
    ("ext-type", "update", lambda n: pk(msgpack.ExtType(1, b"abc")), "BadMessage", False),
    ("int-map-keys", "update", lambda n: pk({1: 2}), "BadMessage", False),
    ("wrong-version", "update", lambda n: pk({**update_dict(n), "v": 2}), "UnsupportedVersion",
     False),
    ("version-as-string", "update", lambda n: pk({**update_dict(n), "v": "1"}),
     "UnsupportedVersion", False),
    ("missing-version", "update", lambda n: pk(_minus(update_dict(n), "v")), "BadMessage", False),
    ("missing-id", "update", lambda n: pk(_minus(update_dict(n), "id")), "BadMessage", False),
    ("unknown-field", "update", lambda n: pk(update_dict(n, extra_field=1)), "BadMessage", False),
    ("shape-N-by-6", "update",
     lambda n: pk(update_dict(n, samples=arr_map(good_samples(n)[:, :6]))), "BadMessage", False),
    ("shape-1d", "update",
     lambda n: pk(update_dict(n, samples=arr_map(good_samples(n).ravel()))), "BadMessage",
     False),
    ("N-plus-one", "update",
     lambda n: pk(update_dict(n, samples=arr_map(good_samples(n + 1)))), "SampleCountMismatch",
     False),
    ("N-minus-one", "update",
     lambda n: pk(update_dict(n, samples=arr_map(good_samples(n - 1)))), "SampleCountMismatch",
     False),
    ("huge-shape-claim", "update",
     lambda n: pk(update_dict(n, samples=arr_map(good_samples(n), shape=[10**9, 7]))),
     "LimitExceeded", False),
    ("data-length-mismatch", "update",
     lambda n: pk(update_dict(n, samples=arr_map(good_samples(n),
                                                 data=good_samples(n).tobytes()[:-8]))),
     "BadMessage", False),
    ("big-endian-dtype", "update",
     lambda n: pk(update_dict(n, samples=arr_map(good_samples(n), dtype=">f8"))), "BadMessage",
     False),
    ("object-dtype", "update",
     lambda n: pk(update_dict(n, samples=arr_map(good_samples(n), dtype="|O"))), "BadMessage",
     False),
    ("samples-not-a-map", "update", lambda n: pk(update_dict(n, samples=[1.0, 2.0])),
     "BadMessage", False),
    ("nan", "update", lambda n: _with(n, _nan), "InvalidSamples", False),
    ("inf", "update", lambda n: _with(n, _inf), "InvalidSamples", False),
    ("zero-quaternion", "update", lambda n: _with(n, _zero_q), "InvalidSamples", False),
    ("non-unit-quaternion", "update", lambda n: _with(n, _long_q), "InvalidSamples", False),
    ("frame-empty-segment", "update", lambda n: pk(update_dict(n, b="r//x")), "BadMessage", False),
    ("frame-with-newline", "update", lambda n: pk(update_dict(n, b="p\n")), "BadMessage", False),
    ("frame-empty", "update", lambda n: pk(update_dict(n, a="")), "BadMessage", False),
    ("frame-129-chars", "update", lambda n: pk(update_dict(n, b="x" * 129)), "BadMessage", False),
    ("frame-not-string", "update", lambda n: pk(update_dict(n, b=17)), "BadMessage", False),
    ("id-too-long", "update", lambda n: pk(update_dict(n, id="i" * 500)), "LimitExceeded",
     False),
    ("self-loop", "update", lambda n: pk(update_dict(n, a="w", b="w")), "InvalidOperation", True),
    ("remove-unknown-frame", "remove", lambda n: pk({"v": 1, "id": "bad-2", "frame": "nope"}),
     "UnknownFrame", True),
    ("remove-bad-name", "remove", lambda n: pk({"v": 1, "id": "bad-3", "frame": "a b"}),
     "BadMessage", False),
    ("query-unknown-frame", "query", lambda n: pk({"v": 1, "id": "q", "a": "w", "b": "nope"}),
     "UnknownFrame", True),
    ("query-not-related", "query", lambda n: pk({"v": 1, "id": "q", "a": "w", "b": "lonely"}),
     "NotRelated", True),
    ("query-bad-want", "query",
     lambda n: pk({"v": 1, "id": "q", "a": "w", "b": "r", "want": "everything"}), "BadMessage",
     False),
    ("relinearize-unknown-frame", "relinearize",
     lambda n: pk({"v": 1, "id": "rl", "frame": "nope"}), "UnknownFrame", True),
    ("relinearize-bad-frame", "relinearize",
     lambda n: pk({"v": 1, "id": "rl", "frame": "a b"}), "BadMessage", False),
    ("relinearize-unknown-field", "relinearize",
     lambda n: pk({"v": 1, "id": "rl", "all": True}), "BadMessage", False),
    ("info-wrong-version", "info", lambda n: pk({"v": 7}), "UnsupportedVersion", False),
    ("submap-bad-op", "submap", lambda n: pk({"v": 1, "id": "s", "op": "merge"}), "BadMessage",
     False),
    ("export-unknown-frame", "submap",
     lambda n: pk({"v": 1, "id": "s", "op": "export", "frame": "nope"}), "UnknownFrame", True),
    ("import-existing-frames", "submap",
     lambda n: wire.encode_submap_import(
         "s", wire.SubmapData("w", ("w", "zz"), (False, False),
                              np.stack([identity(n), good_samples(n)]))), "FrameExists", True),
    ("import-N-off-by-one", "submap",
     lambda n: wire.encode_submap_import(
         "s", wire.SubmapData("k0", ("k0", "k1"), (False, False),
                              np.stack([identity(n + 1), good_samples(n + 1)]))),
     "SampleCountMismatch", False),
]


def decode_for(leaf: str, payload: bytes, n: int) -> object:
    """Decode ``payload`` sent to key leaf ``leaf`` as the server does (the table of
    operations; codec checks only)."""
    return ops.decode_request(leaf, payload, n)[1]
