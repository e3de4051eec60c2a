"""``MapClient``: the Python client of an ``mcsm serve`` map, over Zenoh.

Every call is an acknowledged RPC (a Zenoh ``get`` on ``<prefix>/<map>/<op>``, answered by the
server's queryable), never a fire-and-forget ``put``: the reply is the only proof the server
applied and recorded an update (``shared/notes/ecosystem.md`` §0). Each state-changing request
carries a client-chosen request id; when a call gets no reply in time it is retried with the
*same* id, and the server answers a retried id it already applied with the original
acknowledgement, so a retry never applies an update twice.

Errors the server reports come back as the same typed exception (``McsmError.from_dict``):
``UnknownFrame``, ``SampleCountMismatch``, ``InvalidSamples``, ``BadMessage``, ... No reply
after all attempts raises :class:`mcsm.errors.Timeout`; nothing here waits without a deadline.

Example::

    import numpy as np
    from mcsm_client.client import MapClient

    with MapClient(map="default", timeout_s=5.0) as client:
        ack = client.update("world", "robot", samples)        # (N, 7) x y z qw qx qy qz
        x_world_robot = client.query("world", "robot")        # (N, 7)
        mean, cov = client.marginal("world", "robot")         # (7,), (6, 6)
        print(client.info().digest)
"""

from __future__ import annotations

import itertools
import logging
import queue
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from typing import Any, TypeVar

import numpy as np
import numpy.typing as npt
import zenoh
from mcsm import wire
from mcsm.connect import ZenohConfigLike, client_config
from mcsm.errors import BadMessage, LimitExceeded, McsmError, Timeout

log = logging.getLogger(__name__)

T = TypeVar("T")

DEFAULT_TIMEOUT_S = 10.0


class MapClient:
    """A client session bound to one map of one server.

    Parameters
    ----------
    map : str
        Map name (``<prefix>/<map>/...`` keys).
    connect : str, optional
        Server endpoint. ``None`` means ``tcp/127.0.0.1:7447`` unless ``zenoh_config`` names
        endpoints; when both are given, ``connect`` wins.
    zenoh_config : path, dict or zenoh.Config, optional
        A full Zenoh config (JSON5 file, dict or Config) replacing the loopback defaults.
    timeout_s : float
        Deadline of one attempt of one call, in seconds.
    retries : int
        Extra attempts after a call got no reply (same request id each time).
    prefix : str
        Key expression prefix (default ``mcsm``).
    sender : str, optional
        Name written into the server's recording for this client's inputs (default: the
        Zenoh session id).

    Raises
    ------
    Timeout
        If no server could be reached while opening the session.
    """

    def __init__(self, map: str = wire.DEFAULT_MAP, connect: str | None = None,
                 zenoh_config: ZenohConfigLike = None, timeout_s: float = DEFAULT_TIMEOUT_S,
                 *, retries: int = 2, prefix: str = wire.DEFAULT_PREFIX,
                 sender: str | None = None) -> None:
        if not timeout_s > 0:
            raise ValueError("timeout_s must be positive")
        self.keys = wire.map_keys(map, prefix)
        self.timeout_s = float(timeout_s)
        self.retries = max(0, int(retries))
        conf = client_config(connect, zenoh_config)
        try:
            self.session = zenoh.open(conf)
        except zenoh.ZError as exc:
            raise Timeout(f"connect to {connect or 'the configured endpoints'} ({exc})",
                          self.timeout_s) from None
        self.sender = sender if sender is not None else str(self.session.zid())
        self._id_base = uuid.uuid4().hex[:16]
        self._counter = itertools.count(1)
        self._closed = False

    # ---------------------------------------------------------------- lifecycle
    def close(self) -> None:
        """Close the Zenoh session (idempotent)."""
        if not self._closed:
            self._closed = True
            self.session.close()

    def __enter__(self) -> MapClient:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    @property
    def map(self) -> str:
        return self.keys.map

    def new_request_id(self) -> str:
        """A fresh request id, unique to this client (``<random hex>-<counter>``)."""
        return f"{self._id_base}-{next(self._counter)}"

    # ---------------------------------------------------------------- RPC core
    def _call(self, key: str, payload: bytes, decode: Callable[[bytes], T], what: str,
              timeout_s: float | None = None) -> T:
        """Send ``payload`` to ``key`` and return the decoded single reply, retrying on silence.

        The same payload (hence the same request id) is sent on every attempt.
        """
        if self._closed:
            raise McsmError("the client is closed")
        if len(payload) > wire.MAX_PAYLOAD_BYTES:
            # Zenoh would drop it silently (the caller would only see a Timeout)
            raise LimitExceeded("request bytes", len(payload), wire.MAX_PAYLOAD_BYTES)
        t = self.timeout_s if timeout_s is None else float(timeout_s)
        attempts = self.retries + 1
        for attempt in range(attempts):
            got = self._attempt(key, payload, t)
            if got is None:
                log.warning("%s: no reply within %.3g s (attempt %d of %d)", what, t,
                            attempt + 1, attempts)
                continue
            ok, data = got
            if ok:
                return decode(data)
            raise wire.decode_error(data)
        raise Timeout(what, t)

    def _attempt(self, key: str, payload: bytes, timeout_s: float) -> tuple[bool, bytes] | None:
        """One ``get``; ``(True, payload)``, ``(False, error payload)`` or ``None`` (silence)."""
        replies = self.session.get(key, payload=payload, timeout=timeout_s,
                                   congestion_control=zenoh.CongestionControl.BLOCK)
        result: tuple[bool, bytes] | None = None
        # The handler ends when the query is finalised (every replier done, or zenoh's own
        # timeout); the extra slack only guards against a finalisation that never comes.
        deadline = time.monotonic() + timeout_s + 2.0
        while time.monotonic() < deadline:
            try:
                reply = replies.recv()
            except zenoh.ZError:  # "channel is empty and closed": the query is finalised
                break
            if reply.ok is not None:
                if result is None or not result[0]:
                    result = (True, reply.ok.payload.to_bytes())
                continue
            err_payload = reply.err.payload.to_bytes() if reply.err is not None else b""
            try:
                wire.decode_error(err_payload)
            except McsmError:
                # not an mcsm error reply: zenoh's "Timeout" or a transport error
                log.debug("%s: non-mcsm error reply %r", key, err_payload[:64])
                continue
            if result is None:
                result = (False, err_payload)
        return result

    # ---------------------------------------------------------------- operations
    def update(self, a: str, b: str, samples: npt.ArrayLike, *,
               request_id: str | None = None, timeout_s: float | None = None) -> wire.Ack:
        """Apply the AT ``a -> b`` given as samples ``(N, 7)`` (``x y z qw qx qy qz``).

        Returns the server's :class:`mcsm.wire.Ack` (sequence number, kind: ``new_component``,
        ``new_frame``, ``join`` or ``loop_closure``, component root, frames added).

        Raises
        ------
        SampleCountMismatch, InvalidSamples, BadMessage, InvalidOperation, NumericalError
            As reported by the server (the map is unchanged).
        Timeout
            No reply after all attempts (the update may or may not have been applied; calling
            again with the same ``request_id`` is safe).
        """
        arr = np.asarray(samples, dtype=np.float64)
        if arr.ndim != 2 or arr.shape[1] != 7:
            raise BadMessage("samples", "shape (N, 7)", arr.shape)
        return self._update(a, b, arr, request_id, timeout_s)

    def update_point(self, a: str, b: str, samples3: npt.ArrayLike, *,
                     request_id: str | None = None,
                     timeout_s: float | None = None) -> wire.Ack:
        """Apply an observation of point frame ``b`` from full frame ``a``: samples ``(N, 3)``."""
        arr = np.asarray(samples3, dtype=np.float64)
        if arr.ndim != 2 or arr.shape[1] != 3:
            raise BadMessage("samples", "shape (N, 3)", arr.shape)
        return self._update(a, b, arr, request_id, timeout_s)

    def _update(self, a: str, b: str, arr: np.ndarray, request_id: str | None,
                timeout_s: float | None) -> wire.Ack:
        rid = request_id or self.new_request_id()
        payload = wire.encode_update(rid, a, b, arr, sender=self.sender)
        return self._call(self.keys.update, payload, wire.decode_ack, f"update {a}->{b}",
                          timeout_s)

    def remove(self, frame: str, *, request_id: str | None = None,
               timeout_s: float | None = None) -> wire.Ack:
        """Remove ``frame`` from the map (other estimates and correlations unchanged)."""
        rid = request_id or self.new_request_id()
        payload = wire.encode_remove(rid, frame, sender=self.sender)
        return self._call(self.keys.remove, payload, wire.decode_ack, f"remove {frame}",
                          timeout_s)

    def query(self, a: str, b: str, *, timeout_s: float | None = None) -> np.ndarray:
        """Samples ``(N, 7)`` of the AT ``a -> b`` (a new array; row order is the map's).

        Raises
        ------
        UnknownFrame, NotRelated
        """
        payload = wire.encode_query(self.new_request_id(), a, b, "samples")
        r = self._call(self.keys.query, payload, wire.decode_query_reply, f"query {a}->{b}",
                       timeout_s)
        if r.samples is None:
            raise BadMessage("samples", "samples in the query reply", "none")
        return r.samples

    def marginal(self, a: str, b: str, *,
                 timeout_s: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Mean ``(7,)`` and tangent covariance ``(6, 6)`` (``tx ty tz rx ry rz``) of ``a -> b``."""
        payload = wire.encode_query(self.new_request_id(), a, b, "marginal")
        r = self._call(self.keys.query, payload, wire.decode_query_reply,
                       f"marginal {a}->{b}", timeout_s)
        if r.mean is None or r.cov is None:
            raise BadMessage("mean/cov", "mean and cov in the query reply", "none")
        return r.mean, r.cov

    def info(self, *, timeout_s: float | None = None) -> wire.MapInfo:
        """Frames, components, N, options, sequence number and state digest of the map."""
        return self._call(self.keys.info, wire.encode_info(self.new_request_id()),
                          wire.decode_info_reply, "info", timeout_s)

    def export_submap(self, component: str, *, timeout_s: float | None = None) -> Any:
        """The whole component containing frame ``component`` as the core's ``Submap``
        (root first, all edges, sample order intact)."""
        payload = wire.encode_submap_export(self.new_request_id(), component)
        r = self._call(self.keys.submap, payload, wire.decode_submap_reply,
                       f"export {component}", timeout_s)
        return r.submap.to_core()

    def import_submap(self, submap: Any, *, request_id: str | None = None,
                      timeout_s: float | None = None) -> wire.Ack:
        """Add an exported component (core ``Submap`` or :class:`mcsm.wire.SubmapData`) as a
        new component; its frame names must all be new (``FrameExists`` otherwise)."""
        rid = request_id or self.new_request_id()
        payload = wire.encode_submap_import(rid, submap, sender=self.sender)
        return self._call(self.keys.submap, payload, wire.decode_ack, "import submap",
                          timeout_s)

    def wait_for_server(self, timeout_s: float = 10.0) -> wire.MapInfo:
        """Poll ``info`` until the server answers or ``timeout_s`` passes (then ``Timeout``)."""
        deadline = time.monotonic() + timeout_s
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise Timeout(f"wait for server of map {self.map!r}", timeout_s)
            try:
                return self._call(self.keys.info, wire.encode_info(self.new_request_id()),
                                  wire.decode_info_reply, "info", min(1.0, max(left, 0.05)))
            except Timeout:
                continue

    def servers(self, timeout_s: float = 1.0) -> list[str]:
        """Ids of the live servers serving this map (their liveliness tokens)."""
        prefix = self.keys.alive("")
        out = []
        for reply in self.session.liveliness().get(self.keys.alive_any, timeout=timeout_s):
            if reply.ok is not None:
                key = str(reply.ok.key_expr)
                if key.startswith(prefix):
                    out.append(key[len(prefix):])
        return sorted(out)

    # ---------------------------------------------------------------- events
    def watch(self, callback: Callable[[wire.Event], None] | None = None) -> EventStream:
        """Subscribe to ``<prefix>/<map>/events``.

        With ``callback``, each decoded :class:`mcsm.wire.Event` is passed to it from a
        background thread; otherwise iterate the returned stream or call ``get(timeout_s)``.
        Close the stream (or use it as a context manager) to unsubscribe. Events are a
        best-effort feed (a Zenoh ``put``): a slow or late subscriber may miss some; the
        sequence numbers show gaps.
        """
        return EventStream(self.session, self.keys.events, callback)


class EventStream:
    """Decoded events of one map; iterate, ``get(timeout_s)``, or pass a callback."""

    def __init__(self, session: zenoh.Session, key: str,
                 callback: Callable[[wire.Event], None] | None = None) -> None:
        self._q: queue.Queue[wire.Event] = queue.Queue(maxsize=100_000)
        self._callback = callback
        self._closed = threading.Event()
        self.dropped = 0
        self._sub = session.declare_subscriber(key, self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        try:
            ev = wire.decode_event(sample.payload.to_bytes())
        except McsmError as exc:
            log.warning("undecodable event on %s: %s", sample.key_expr, exc)
            return
        if self._callback is not None:
            try:
                self._callback(ev)
            except Exception:  # a user callback must not kill zenoh's thread
                log.exception("event callback failed")
            return
        try:
            self._q.put_nowait(ev)
        except queue.Full:
            self.dropped += 1

    def get(self, timeout_s: float) -> wire.Event | None:
        """The next event, or ``None`` if none arrives within ``timeout_s``."""
        try:
            return self._q.get(timeout=timeout_s)
        except queue.Empty:
            return None

    def __iter__(self) -> Iterator[wire.Event]:
        """Events until :meth:`close` (checks for closing every 0.2 s)."""
        while not self._closed.is_set():
            ev = self.get(0.2)
            if ev is not None:
                yield ev

    def close(self) -> None:
        if not self._closed.is_set():
            self._closed.set()
            self._sub.undeclare()

    def __enter__(self) -> EventStream:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()
