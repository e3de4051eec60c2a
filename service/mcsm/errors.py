"""One small hierarchy of typed errors, shared by the core, the wire codec, the server and clients.

Every error keeps its facts as attributes and builds its message from them, so a server can
turn any :class:`McsmError` into a structured error reply (``to_dict``) and a client can rebuild
the same type from that reply (``from_dict``).
"""

from __future__ import annotations

from typing import Any


class McsmError(Exception):
    """Root of every error mcsm raises on purpose."""

    retryable = False
    """True for errors a client retries with the same request id until its deadline."""

    def __init__(self, message: str, **fields: Any) -> None:
        super().__init__(message)
        self.message = message
        self.fields = fields

    def to_dict(self) -> dict[str, Any]:
        """The error as a plain dict (``error``, ``message``, ``fields``) for an error reply."""
        return {"error": type(self).__name__, "message": self.message,
                "fields": _plain(self.fields)}

    @staticmethod
    def from_dict(d: dict[str, Any]) -> McsmError:
        """Rebuild a typed error from :meth:`to_dict` output (unknown names give McsmError)."""
        cls = _REGISTRY.get(str(d.get("error")), McsmError)
        err = cls.__new__(cls)
        McsmError.__init__(err, str(d.get("message", "")), **dict(d.get("fields") or {}))
        return err


def _plain(fields: dict[str, Any]) -> dict[str, Any]:
    return {k: (v if isinstance(v, (int, float, str, bool, type(None))) else str(v))
            for k, v in fields.items()}


class BadMessage(McsmError):
    """A field of an input has the wrong type, shape, dtype or value."""

    def __init__(self, field: str, expected: str, got: Any) -> None:
        super().__init__(f"bad {field}: expected {expected}, got {got}",
                         field=field, expected=expected, got=str(got))


class UnsupportedVersion(McsmError):
    """A message carries a protocol version this build does not speak."""

    def __init__(self, got: Any, supported: int) -> None:
        super().__init__(f"unsupported message version {got!r} (this server speaks {supported})",
                         got=str(got), supported=supported)


class InvalidSamples(McsmError):
    """An AT sample set is unusable: non-finite values, non-unit quaternions, wrong layout."""

    def __init__(self, reason: str) -> None:
        super().__init__(f"invalid samples: {reason}", reason=reason)


class SampleCountMismatch(McsmError):
    """A sample set has a number of samples other than the map's N."""

    def __init__(self, expected: int, got: int) -> None:
        super().__init__(f"sample count mismatch: the map uses N={expected}, got {got}",
                         expected=expected, got=got)


class UnknownFrame(McsmError):
    """A frame named in a query or remove is not in the map."""

    def __init__(self, name: str) -> None:
        super().__init__(f"unknown frame {name!r}", name=name)


class FrameExists(McsmError):
    """A frame that must be new (an imported submap's) is already in the map."""

    def __init__(self, name: str) -> None:
        super().__init__(f"frame {name!r} already exists", name=name)


class InvalidOperation(McsmError):
    """The operation is well-formed but not allowed (a == b, under-determined join, ...)."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason, reason=reason)


class NotRelated(McsmError):
    """Two frames are in different components: no relation between them is known."""

    def __init__(self, a: str, b: str) -> None:
        super().__init__(f"frames {a!r} and {b!r} are in different components", a=a, b=b)


class NumericalError(McsmError):
    """An update would produce non-finite or invalid samples; it was refused, the map unchanged."""

    def __init__(self, reason: str) -> None:
        super().__init__(f"update refused: {reason}", reason=reason)


class LimitExceeded(McsmError):
    """An input exceeds a configured limit (payload bytes, samples, name length, queue)."""

    def __init__(self, what: str, value: Any, limit: Any) -> None:
        super().__init__(f"{what} {value} exceeds the limit {limit}",
                         what=what, value=str(value), limit=str(limit))


class Busy(LimitExceeded):
    """The server's request queue is full (by count, or by bytes of queued requests: ``what``
    says which): nothing was applied; retry later with the same id."""

    def __init__(self, queue_length: int, limit: int,
                 what: str = "request queue length") -> None:
        super().__init__(what, queue_length, limit)


class DeviceMemoryExceeded(LimitExceeded):
    """A map on a GPU (``device="cuda"``) would need more device memory than is free: the
    request was refused before anything changed."""

    def __init__(self, what: str, needed: int, free: int) -> None:
        McsmError.__init__(
            self, f"{what} needs {needed} bytes of device memory, {free} are free: refused, "
            f"nothing changed", what=what, value=str(needed), limit=str(free))


class RequestIdReused(McsmError):
    """A request id the server remembers was sent again with a *different* request.

    Nothing was applied; the remembered request keeps its ack. Send the new request with a
    fresh id (``MapClient`` makes unique ids unless told one).
    """

    def __init__(self, request_id: str, seq: int) -> None:
        super().__init__(f"request id {request_id!r} was already used for another request "
                         f"(applied as seq {seq}); use a fresh id", request_id=request_id,
                         seq=seq)


class Forbidden(McsmError):
    """A write outside the namespace the request's key grants (``<prefix>/<map>/update/<ns>``).

    The access-control list lets a robot's identity use only its own key, so the key names
    the writer; the server refuses frames outside that namespace. Nothing was applied.
    """

    def __init__(self, key: str, frame: str, namespace: str, reason: str) -> None:
        super().__init__(f"{reason}: frame {frame!r} is not in namespace {namespace!r} "
                         f"(key {key})", key=key, frame=frame, namespace=namespace,
                         reason=reason)


class NotReplicated(McsmError):
    """The map's log did not take the update, or this server may not acknowledge it now
    (``mcsm serve --nats``: it does not hold the map's lease, or the lease may have expired
    while the log stored it). It may or may not be in the log; retry with the same request
    id (``MapClient`` does, until its deadline, finding the lease's holder): the retry is
    applied once, or acknowledged as a duplicate if the log holds it.
    """

    retryable = True

    def __init__(self, map_name: str, reason: str) -> None:
        super().__init__(f"map {map_name!r}: {reason}; retry with the same request id",
                         map=map_name, reason=reason)


class InternalError(McsmError):
    """An unexpected server-side failure (logged there with its traceback); nothing applied."""

    def __init__(self, reason: str) -> None:
        super().__init__(f"internal error: {reason}", reason=reason)


class Timeout(McsmError):
    """A request got no answer in time (client side)."""

    def __init__(self, what: str, timeout_s: float) -> None:
        super().__init__(f"{what}: no reply within {timeout_s:g} s", what=what,
                         timeout_s=timeout_s)


class NoServer(Timeout):
    """No live server serves the map (no liveliness token) within the call's timeout."""

    def __init__(self, map_name: str, token_key: str, timeout_s: float,
                 served: list[str] | None = None) -> None:
        seen = ("" if served is None else
                f"; maps served here: {', '.join(served)}" if served else
                "; no map is served here (no server, or none this identity may see)")
        McsmError.__init__(
            self, f"no server serves map {map_name!r} (no liveliness token on {token_key}) "
            f"within {timeout_s:g} s{seen}", what="wait for server", map=map_name,
            key=token_key, timeout_s=timeout_s)


class Unreachable(Timeout):
    """The client's Zenoh session could not connect to any endpoint (nothing listens there, or
    the network refuses): said at once, after Zenoh's own connect timeout."""

    def __init__(self, where: str, connect_timeout_s: float, detail: str = "",
                 listening: bool = False) -> None:
        hint = ("something listens there but did not complete Zenoh's handshake: it wants "
                "credentials or TLS (--zenoh-config with this identity's config, "
                "docs/deploy.md), or it is not a Zenoh endpoint" if listening else
                "is `mcsm serve` (or a router) running there?")
        McsmError.__init__(
            self, f"cannot connect to {where}: no Zenoh session opened within Zenoh's connect "
            f"timeout, {connect_timeout_s:g} s{f' ({detail})' if detail else ''}; {hint}",
            what="connect", where=where, timeout_s=connect_timeout_s)


class NoPermittedServer(Timeout):
    """The map's server is alive, but every request on this key got no reply at all.

    Zenoh delivers no reply when an access-control list denies the request (or nobody
    serves that key): retrying does not help; check the identity's rights on the key.
    """

    def __init__(self, key: str, server_id: str, timeout_s: float) -> None:
        McsmError.__init__(
            self, f"no permitted server for {key}: server {server_id} is alive but every "
            f"request got no reply for {timeout_s:g} s (denied by the access-control list: a "
            "robot's identity writes only with --namespace NAME; or a key it does not serve)",
            what=key, key=key, server_id=server_id, timeout_s=timeout_s)


_REGISTRY: dict[str, type[McsmError]] = {
    c.__name__: c
    for c in (McsmError, BadMessage, UnsupportedVersion, InvalidSamples, SampleCountMismatch,
              UnknownFrame, FrameExists, InvalidOperation, NotRelated, NumericalError,
              LimitExceeded, Busy, DeviceMemoryExceeded, RequestIdReused, Forbidden,
              NotReplicated, InternalError,
              Timeout,
              NoServer, NoPermittedServer, Unreachable)
}
