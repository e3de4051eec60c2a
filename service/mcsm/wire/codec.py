"""The wire's codecs: encode (clients) and decode (server, replay) every request, and the
server's replies, error replies and events, each through the checks of
:mod:`mcsm.wire.checks` into the dataclasses of :mod:`mcsm.wire.messages`.
"""

from __future__ import annotations

from typing import Any

import numpy.typing as npt

from mcsm.errors import BadMessage, McsmError
from mcsm.wire.checks import (
    MAX_ID_CHARS,
    MAX_INFO_FRAMES,
    MAX_PAYLOAD_BYTES,
    MAX_REPLY_BYTES,
    MAX_SENDER_CHARS,
    VERSION,
    QueryWant,
    _int,
    _keys,
    _request_id,
    _str,
    check_frame,
    decode_samples,
    from_message_dict,
    message_dict,
    pack,
    pack_array,
    short,
    unpack,
)
from mcsm.wire.messages import (
    Ack,
    Event,
    InfoRequest,
    MapInfo,
    QueryReply,
    QueryRequest,
    RelinearizeRequest,
    RemoveRequest,
    RetractRequest,
    SubmapData,
    SubmapExportRequest,
    SubmapImportRequest,
    SubmapReply,
    UpdateRequest,
    VerdictRequest,
    _pack_submap,
    decode_submap_data,
    submap_from_core,
)

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


def encode_submap_import(request_id: str, submap: SubmapData | Any, sender: str = "") -> bytes:
    """An import request; ``submap`` is a :class:`SubmapData` or the core's ``Submap``."""
    sub = submap if isinstance(submap, SubmapData) else submap_from_core(submap)
    d: dict[str, Any] = {"v": VERSION, "id": request_id, "op": "import",
                         "submap": _pack_submap(sub)}
    if sender:
        d["sender"] = sender
    return pack(d)


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
    # every frame, and one entry per component: bounded by the reply's bytes
    return from_message_dict(MapInfo, unpack(payload, max_bytes=MAX_REPLY_BYTES,
                                             max_map_len=MAX_INFO_FRAMES,
                                             max_array_len=MAX_INFO_FRAMES))


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
