"""One small hierarchy of typed errors, shared by the core, the wire codec, the server and clients.

Every error keeps its facts as attributes and builds its message from them, so a server can
turn any :class:`McsmError` into a structured error reply (``to_dict``) and a client can rebuild
the same type from that reply (``from_dict``).
"""

from __future__ import annotations

from typing import Any


class McsmError(Exception):
    """Root of every error mcsm raises on purpose."""

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
    """The server's request queue is full: nothing was applied; retry later with the same id."""

    def __init__(self, queue_length: int, limit: int) -> None:
        super().__init__("request queue length", queue_length, limit)


class InternalError(McsmError):
    """An unexpected server-side failure (logged there with its traceback); nothing applied."""

    def __init__(self, reason: str) -> None:
        super().__init__(f"internal error: {reason}", reason=reason)


class Timeout(McsmError):
    """A request got no answer in time (client side)."""

    def __init__(self, what: str, timeout_s: float) -> None:
        super().__init__(f"{what}: no reply within {timeout_s} s", what=what, timeout_s=timeout_s)


_REGISTRY: dict[str, type[McsmError]] = {
    c.__name__: c
    for c in (McsmError, BadMessage, UnsupportedVersion, InvalidSamples, SampleCountMismatch,
              UnknownFrame, FrameExists, InvalidOperation, NotRelated, NumericalError,
              LimitExceeded, Busy, InternalError, Timeout)
}
