"""``MapClient``: the Python client of an ``mcsm serve`` map, over Zenoh.

Every call is an acknowledged RPC (a Zenoh ``get`` on ``<prefix>/<map>/<op>``, answered by the
server's queryable), never a fire-and-forget ``put``: the reply is the only proof the server
applied and recorded an update (a Zenoh ``put`` can be dropped silently). Each state-changing
request carries a client-chosen request id; when an attempt gets no reply it is sent again with the
*same* id, and the server answers a retried id it already applied with the original
acknowledgement, so a retry never applies an update twice (ids are remembered for ten minutes
by default, across a ``--restore`` too).

**Which replies count.** The client finds the map's server by its liveliness token
``<prefix>/<map>/alive/<zid>`` and accepts a reply only when Zenoh's replier id is that
``zid`` (and the ack names it); any other reply is counted in :attr:`MapClient.foreign_replies`
and logged, never returned.

**Waiting.** A call waits for the server up to its own ``timeout_s``, sending again with
backoff (0.05 s doubling to 1 s) while nobody answers, so it resumes when a restarted server
comes back. When the deadline passes it raises one of three :class:`mcsm.errors.Timeout`
kinds that say why: :class:`~mcsm.errors.NoServer` (no live server token),
:class:`~mcsm.errors.NoPermittedServer` (the server is alive but the request got no reply at
all: an access-control list denies it) or ``Timeout`` itself (the server is alive but did not
answer in time). Nothing here waits without a deadline.

Errors the server reports come back as the same typed exception (``McsmError.from_dict``):
``UnknownFrame``, ``SampleCountMismatch``, ``InvalidSamples``, ``BadMessage``, ``Forbidden``,
``RequestIdReused``, ...

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
import json
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
from mcsm.errors import (
    BadMessage,
    LimitExceeded,
    McsmError,
    NoPermittedServer,
    NoServer,
    Timeout,
    Unreachable,
)
from mcsm.map import ops
from mcsm.serve.connect import ZenohConfigLike, client_config, listening_at, zenoh_error_text

log = logging.getLogger(__name__)

T = TypeVar("T")

DEFAULT_TIMEOUT_S = 10.0
BACKOFF_FIRST_S = 0.05
BACKOFF_MAX_S = 1.0
MIN_ATTEMPT_S = 0.02
"""An attempt with less time left than this is not started (the call ends)."""


def _connect_timeout_s(conf: zenoh.Config) -> float:
    """Zenoh's ``connect/timeout_ms`` of a config, in seconds (how long ``zenoh.open`` tried)."""
    try:
        return float(json.loads(conf.get_json("connect/timeout_ms"))) / 1000.0
    except (zenoh.ZError, ValueError, TypeError):
        return float("nan")


class MapClient:
    """A client session bound to one map of one server.

    Parameters
    ----------
    map : str
        Map name (``<prefix>/<map>/...`` keys).
    connect : str, optional
        Server endpoint. ``None`` means the default (``mcsm.serve.connect.DEFAULT_ENDPOINT``) unless
        ``zenoh_config`` (or ``ZENOH_CONFIG``) names endpoints; when both are given,
        ``connect`` wins.
    zenoh_config : path, dict or zenoh.Config, optional
        A full Zenoh config (JSON5 file, dict or Config) replacing the loopback defaults, e.g.
        one of ``deploy/``'s role configs.
    timeout_s : float
        Deadline of one call, in seconds: the call keeps trying (same request id, backoff)
        until it gets the server's answer or this much time has passed.
    retries : int, optional
        Ignored (calls retry until their deadline); accepted so older callers still run.
    prefix : str
        Key expression prefix (default ``mcsm``).
    sender : str, optional
        Name written into the server's recording for this client's inputs (default: the
        Zenoh session id).
    namespace : str, optional
        Send updates and removes on ``<prefix>/<map>/update/<namespace>`` and
        ``remove/<namespace>``: the keys a robot's identity is granted by the shipped
        access-control lists. The server then refuses frames outside the namespace
        (``Forbidden``). ``None``: the unrestricted keys (admin, or no access control).
    server_id : str, optional
        Accept replies only from the server with this Zenoh id. ``None``: the one server whose
        liveliness token is visible (several tokens for one map are refused as ambiguous).

    Raises
    ------
    Unreachable
        If the Zenoh session could not connect to any endpoint (a :class:`Timeout`).
    """

    def __init__(self, map: str = wire.DEFAULT_MAP, connect: str | None = None,
                 zenoh_config: ZenohConfigLike = None, timeout_s: float = DEFAULT_TIMEOUT_S,
                 *, retries: int | None = None, prefix: str = wire.DEFAULT_PREFIX,
                 sender: str | None = None, namespace: str | None = None,
                 server_id: str | None = None) -> None:
        del retries  # calls retry until their own deadline
        if not timeout_s > 0:
            raise ValueError("timeout_s must be positive")
        self.keys = wire.map_keys(map, prefix)
        self.timeout_s = float(timeout_s)
        self.namespace = wire.check_namespace(namespace) if namespace is not None else None
        self._pinned = server_id
        self._server: str | None = server_id
        self._answered = threading.local()  # per calling thread: the server that answered
        self.foreign_replies = 0
        """Replies from anyone but the map's server (ignored and logged)."""
        conf = client_config(connect, zenoh_config)
        try:
            self.session = zenoh.open(conf)
        except zenoh.ZError as exc:
            raise Unreachable(connect or "the configured endpoints", _connect_timeout_s(conf),
                              f"Zenoh: {zenoh_error_text(exc)}",
                              listening=bool(listening_at(conf))) from None
        self.sender = sender if sender is not None else str(self.session.zid())
        self._id_base = uuid.uuid4().hex[:16]
        self._counter = itertools.count(1)
        self._closed = False
        # the attempt in flight (its server and reply queue): if that server's token goes away
        # (it died: a standby takes over) the attempt ends at once instead of at its timeout
        self._waiting: tuple[str, zenoh.CancellationToken] | None = None
        self._alive_sub = self.session.liveliness().declare_subscriber(
            self.keys.alive_any, self._on_alive)

    def _on_alive(self, sample: zenoh.Sample) -> None:
        if sample.kind != zenoh.SampleKind.DELETE:
            return
        zid = str(sample.key_expr).rsplit("/", 1)[-1]
        if self._pinned is None and self._server == zid:
            self._server = None  # the next call looks for the map's server again
        waiting = self._waiting
        if waiting is not None and waiting[0] == zid:
            waiting[1].cancel()

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
    @property
    def server_id(self) -> str | None:
        """Zenoh id of the server this client last talked to (``None`` before the first call
        or while no server is visible)."""
        return self._server

    def _resolve_server(self, timeout_s: float) -> str | None:
        """The id of the map's one live server (liveliness token), or None if none is seen.

        Raises
        ------
        McsmError
            If several servers claim the map and none was pinned with ``server_id``.
        """
        ids = self.servers(timeout_s=max(0.05, min(1.0, timeout_s)))
        if self._pinned is not None:
            return self._pinned if self._pinned in ids else None
        if len(ids) > 1:
            raise McsmError(f"{len(ids)} servers claim map {self.map!r} ({', '.join(ids)}); "
                            "pass server_id= to choose one (or fix the access control: only "
                            "the server identity may declare tokens on the map's keys)",
                            servers=",".join(ids))
        return ids[0] if ids else None

    def _call(self, key: str, payload: bytes, decode: Callable[[bytes], T], what: str,
              timeout_s: float | None = None) -> T:
        """Send ``payload`` to ``key`` until the map's server answers or the deadline passes.

        The same payload (hence the same request id) is sent every time, with backoff
        between attempts that got no answer.
        """
        if self._closed:
            raise McsmError("the client is closed")
        if len(payload) > wire.MAX_PAYLOAD_BYTES:
            # Zenoh would drop it silently (the caller would only see a Timeout)
            raise LimitExceeded("request bytes", len(payload), wire.MAX_PAYLOAD_BYTES)
        t = self.timeout_s if timeout_s is None else float(timeout_s)
        deadline = time.monotonic() + t
        delay = BACKOFF_FIRST_S
        state, last_server = "none", ""
        # time spent in each state; the one that took most of the deadline names the failure
        spent = {"none": 0.0, "silent": 0.0, "slow": 0.0}
        attempt = 0
        last_error: McsmError | None = None
        while True:
            t_iter = time.monotonic()
            left = deadline - t_iter
            if left < MIN_ATTEMPT_S:
                break
            if self._server is None:
                self._server = self._resolve_server(left)
            left = deadline - time.monotonic()
            server = self._server  # the liveliness callback may reset it meanwhile
            if server is not None and left >= MIN_ATTEMPT_S:
                attempt += 1
                last_server = server
                got = self._attempt(key, payload, left, server)
                if isinstance(got, tuple):
                    ok, data = got
                    if ok:
                        self._answered.server = server  # what _decode_ack checks against
                        return decode(data)
                    err = wire.decode_error(data)
                    if not err.retryable or deadline - time.monotonic() < MIN_ATTEMPT_S:
                        raise err
                    # e.g. NotReplicated: the same request id again after a backoff
                    log.info("%s: %s; retrying", what, err)
                    state = "slow"
                    last_error = err
                else:
                    state = got  # "slow" (zenoh's own timeout) or "silent" (no reply at all)
                    if got == "silent" and self._pinned is None:
                        self._server = None  # it may have restarted under a new id
            else:
                state = "none"
            left = deadline - time.monotonic()
            if left >= MIN_ATTEMPT_S:
                log.info("%s: %s; trying again in %.2g s (%.3g s left of %.3g s)", what,
                         {"none": "no live server", "slow": "no reply yet",
                          "silent": "no reply at all"}[state], min(delay, left), left, t)
                time.sleep(min(delay, left))
                delay = min(2 * delay, BACKOFF_MAX_S)
            spent[state] += time.monotonic() - t_iter
        cause = max(spent, key=lambda k: spent[k]) if attempt else "none"
        log.info("%s: gave up after %.3g s (%d attempts; %s)", what, t, attempt,
                 ", ".join(f"{k} {v:.2g} s" for k, v in spent.items()))
        if last_error is not None and cause == "slow":
            raise last_error
        if cause == "none":
            raise NoServer(self.map, self.keys.alive_any, t, self.served_maps())
        if cause == "silent":
            raise NoPermittedServer(key, last_server, t)
        raise Timeout(f"{what} (server {last_server} is alive but did not answer)", t)

    def _attempt(self, key: str, payload: bytes, timeout_s: float,
                 server: str) -> tuple[bool, bytes] | str:
        """One ``get`` to every queryable on ``key``; the server's ``(ok, payload)``, or
        ``"slow"`` (Zenoh's own timeout reply) or ``"silent"`` (no reply at all)."""
        token = zenoh.CancellationToken()
        self._waiting = (server, token)
        try:
            replies = self.session.get(key, payload=payload, timeout=timeout_s,
                                       congestion_control=zenoh.CongestionControl.BLOCK,
                                       target=zenoh.QueryTarget.ALL,
                                       consolidation=zenoh.ConsolidationMode.NONE,
                                       cancellation_token=token)
            got = self._collect(key, replies, timeout_s, server)
        except zenoh.ZError:
            if not token.is_cancelled:
                raise
            got = "silent"  # the server went away before the query left
        finally:
            self._waiting = None
        if token.is_cancelled and not isinstance(got, tuple):
            # the server died with the request: ask whoever serves the map now
            log.info("%s: server %s went away", key, server)
            return "silent"
        return got

    def _collect(self, key: str, replies: Any, timeout_s: float,
                 server: str) -> tuple[bool, bytes] | str:
        outcome = "silent"
        # The handler ends when the query is finalised (every replier done, zenoh's own
        # timeout, or cancelled: the server's token went away); the extra slack only guards
        # against a finalisation that never comes.
        t0 = time.monotonic()
        deadline = t0 + timeout_s + 2.0
        while time.monotonic() < deadline:
            try:
                reply = replies.recv()
            except zenoh.ZError:  # "channel is empty and closed": the query is finalised
                break
            replier = reply.replier_id
            from_server = replier is not None and str(replier.zid) == server
            if reply.ok is not None:
                data = reply.ok.payload.to_bytes()
                if from_server:
                    return True, data
                self._foreign(key, replier, "reply")
                continue
            err_payload = reply.err.payload.to_bytes() if reply.err is not None else b""
            try:
                wire.decode_error(err_payload)
            except McsmError:
                # not an mcsm error reply: zenoh's own "Timeout" (the server is slow)
                log.debug("%s: non-mcsm error reply %r", key, err_payload[:64])
                if replier is None:
                    outcome = "slow"
                continue
            if from_server:
                return False, err_payload
            self._foreign(key, replier, "error reply")
        if outcome == "silent" and time.monotonic() - t0 >= 0.9 * timeout_s:
            outcome = "slow"  # it ran out its time: that is not the instant silence of a denial
        return outcome

    def _foreign(self, key: str, replier: Any, what: str) -> None:
        self.foreign_replies += 1
        log.warning("%s: ignored a %s from %s, not the map's server %s (%d so far)", key,
                    what, replier.zid if replier is not None else "an unknown replier",
                    self._server, self.foreign_replies)

    def _decode_ack(self, data: bytes) -> wire.Ack:
        ack = wire.decode_ack(data)
        # the server that answered (self._server may have been reset meanwhile by the
        # liveliness callback: the old primary's token went away during a takeover)
        server = getattr(self._answered, "server", None)
        if ack.server and ack.server != server:
            raise BadMessage("ack.server", f"the map's server {server}", ack.server)
        return ack

    def _request(self, name: str, what: str, timeout_s: float | None, request_id: str | None,
                 *args: Any, **kwargs: Any) -> Any:
        """Send operation ``name`` of the table (:mod:`mcsm.map.ops`): its encoder's payload to
        its key (the namespaced one for a namespaced operation of a namespaced client), its
        reply decoded by its decoder (an ack also names the map's server)."""
        op = ops.get(name)
        key = self.keys.request(op.leaf, (self.namespace or "") if op.namespaced else "")
        payload = op.encode(request_id or self.new_request_id(), *args, **kwargs)
        decode = self._decode_ack if op.decode_reply is wire.decode_ack else op.decode_reply
        return self._call(key, payload, decode, what, timeout_s)

    # ---------------------------------------------------------------- operations
    def update(self, a: str, b: str, samples: npt.ArrayLike, *,
               request_id: str | None = None, timeout_s: float | None = None,
               trusted: bool = False, stamp_ns: int | None = None) -> wire.Ack:
        """Apply the AT ``a -> b`` given as samples ``(N, 7)`` (``x y z qw qx qy qz``), or, given
        ``(N, 3)`` samples, the point frame ``b`` seen from ``a`` (as :meth:`update_point` and
        ``StochasticMap.update`` do).

        Returns the server's :class:`mcsm.wire.Ack` (sequence number, kind: ``new_component``,
        ``new_frame``, ``join``, ``loop_closure`` or ``rejected``, component root, frames
        added) with its ``verdict`` (status, the gate's NIS, dof and threshold, reason).
        ``trusted`` bypasses the server's loop-closure gate; ``stamp_ns`` is the source's
        measurement time, recorded and returned in the verdict.

        Raises
        ------
        SampleCountMismatch, InvalidSamples, BadMessage, InvalidOperation, NumericalError
            As reported by the server (the map is unchanged).
        Timeout
            No reply after all attempts (the update may or may not have been applied; calling
            again with the same ``request_id`` is safe).
        """
        arr = np.asarray(samples, dtype=np.float64)
        if arr.ndim != 2 or arr.shape[1] not in (7, 3):
            raise BadMessage("samples", "shape (N, 7) for an AT, or (N, 3) for a point "
                             "(update_point)", arr.shape)
        return self._update(a, b, arr, request_id, timeout_s, trusted, stamp_ns)

    def update_point(self, a: str, b: str, samples3: npt.ArrayLike, *,
                     request_id: str | None = None, timeout_s: float | None = None,
                     trusted: bool = False, stamp_ns: int | None = None) -> wire.Ack:
        """Apply an observation of point frame ``b`` from full frame ``a``: samples ``(N, 3)``."""
        arr = np.asarray(samples3, dtype=np.float64)
        if arr.ndim != 2 or arr.shape[1] != 3:
            raise BadMessage("samples", "shape (N, 3)", arr.shape)
        return self._update(a, b, arr, request_id, timeout_s, trusted, stamp_ns)

    def _update(self, a: str, b: str, arr: np.ndarray, request_id: str | None,
                timeout_s: float | None, trusted: bool = False,
                stamp_ns: int | None = None) -> wire.Ack:
        ack: wire.Ack = self._request("update", f"update {a}->{b}", timeout_s, request_id, a, b,
                                      arr, sender=self.sender, trusted=trusted,
                                      stamp_ns=stamp_ns)
        return ack

    def remove(self, frame: str, *, request_id: str | None = None,
               timeout_s: float | None = None) -> wire.Ack:
        """Remove ``frame`` from the map (other estimates and correlations unchanged)."""
        ack: wire.Ack = self._request("remove", f"remove {frame}", timeout_s, request_id, frame,
                                      sender=self.sender)
        return ack

    def retract(self, target: str, *, request_id: str | None = None,
                timeout_s: float | None = None) -> wire.Ack:
        """Take back the update whose request id is ``target``: the server restores its last
        snapshot before it and applies every later input again without it (bit-identical to a
        map that never had it). The ack's verdict is the target's (``retracted``); events
        list the verdicts that changed. Refused (``InvalidOperation``) when the target is not
        an update of the retract window or is already retracted."""
        ack: wire.Ack = self._request("retract", f"retract {target}", timeout_s, request_id,
                                      target, sender=self.sender)
        return ack

    def reinstate(self, target: str, *, request_id: str | None = None,
                  timeout_s: float | None = None) -> wire.Ack:
        """Put back a retracted update, or one the gate rejected (as if it had always been
        applied, gate bypassed)."""
        ack: wire.Ack = self._request("reinstate", f"reinstate {target}", timeout_s, request_id,
                                      target, sender=self.sender)
        return ack

    def relinearize(self, frame: str = "", *, request_id: str | None = None,
                    timeout_s: float | None = None) -> wire.Ack:
        """Relinearise ``frame``'s component (empty: every component): the map solves for the
        maximum a posteriori estimate of every input it recorded and redraws the component's
        samples from the posterior. Recorded and acknowledged like an update; ``ack.relin``
        says what it did (per component: frames, variables, factors, iterations, cost before
        and after, or why it was skipped; the time it held the worker). Admin only under the
        shipped access control."""
        ack: wire.Ack = self._request("relinearize", f"relinearize {frame or 'all'}", timeout_s,
                                      request_id, frame, sender=self.sender)
        return ack

    def verdict(self, target: str, *, timeout_s: float | None = None) -> wire.Verdict | None:
        """The current verdict of a past request (None for a remove or an import)."""
        ack: wire.Ack = self._request("verdict", f"verdict {target}", timeout_s, None, target)
        return ack.verdict

    def query(self, a: str, b: str, *, timeout_s: float | None = None) -> np.ndarray:
        """Samples ``(N, 7)`` of the AT ``a -> b`` (a new array; row order is the map's).

        Raises
        ------
        UnknownFrame, NotRelated
        """
        r: wire.QueryReply = self._request("query", f"query {a}->{b}", timeout_s, None, a, b,
                                           "samples")
        if r.samples is None:
            raise BadMessage("samples", "samples in the query reply", "none")
        return r.samples

    def marginal(self, a: str, b: str, *,
                 timeout_s: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Mean ``(7,)`` and tangent covariance ``(6, 6)`` (``tx ty tz rx ry rz``) of ``a -> b``."""
        r: wire.QueryReply = self._request("query", f"marginal {a}->{b}", timeout_s, None, a,
                                           b, "marginal")
        if r.mean is None or r.cov is None:
            raise BadMessage("mean/cov", "mean and cov in the query reply", "none")
        return r.mean, r.cov

    def info(self, *, timeout_s: float | None = None) -> wire.MapInfo:
        """Frames, components, N, options, sequence number and state digest of the map."""
        info: wire.MapInfo = self._request("info", "info", timeout_s, None)
        return info

    def export_submap(self, component: str, *, timeout_s: float | None = None) -> Any:
        """The whole component containing frame ``component`` as the core's ``Submap``
        (root first, all edges, sample order intact)."""
        r: wire.SubmapReply = self._request("export", f"export {component}", timeout_s, None,
                                            component)
        return r.submap.to_core()

    def import_submap(self, submap: Any, *, request_id: str | None = None,
                      timeout_s: float | None = None) -> wire.Ack:
        """Add an exported component (core ``Submap`` or :class:`mcsm.wire.SubmapData`) as a
        new component; its frame names must all be new (``FrameExists`` otherwise)."""
        ack: wire.Ack = self._request("import", "import submap", timeout_s, request_id, submap,
                                      sender=self.sender)
        return ack

    def wait_for_server(self, timeout_s: float = 10.0) -> wire.MapInfo:
        """``info``, waiting up to ``timeout_s`` for the server (``NoServer``/``Timeout``)."""
        return self.info(timeout_s=timeout_s)

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

    def served_maps(self, timeout_s: float = 1.0) -> list[str]:
        """Names of the maps under this client's prefix that a live server serves (their
        liveliness tokens, as far as this session may see them)."""
        head = f"{self.keys.prefix}/"
        out: set[str] = set()
        try:
            for reply in self.session.liveliness().get(f"{head}*/alive/*", timeout=timeout_s):
                if reply.ok is not None:
                    key = str(reply.ok.key_expr)
                    if key.startswith(head):
                        out.add(key[len(head):].split("/", 1)[0])
        except zenoh.ZError as exc:
            log.debug("served maps: %s", exc)
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
