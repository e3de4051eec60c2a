"""The map server: Zenoh queryables in front of one worker thread that owns the maps.

Threads and ownership:

* Each map has **one** queryable on ``<prefix>/<map>/**``: Zenoh runs its callbacks one at a
  time, in arrival order, on that entity's thread, so everything one client session sends to a
  map, on any of its keys, is decoded and queued in the order it arrived (a short ``remove``
  cannot overtake a long ``update``). The callback routes on the concrete key (a wildcard key
  is refused), decodes and checks the payload with :mod:`mcsm.wire`, checks a namespaced key's
  frames (``update/<ns>``, ``remove/<ns>``), and puts the request on the worker's queue
  (:mod:`mcsm.serve.lanes`): changes on the write lane, reads on the read lane, each bounded in
  count (``--queue-size``) and in payload bytes (``--queue-bytes``). A full lane is answered
  at once with a ``Busy`` error (a ``LimitExceeded``): the client may retry later with the
  same request id.
* One worker thread owns every :class:`~mcsm.state.MapState` and the
  :class:`~mcsm.log.writer.Recorder`. It takes requests in arrival order, assigns each applied
  operation the map's next sequence number, applies it through the core, records it (flushed),
  and only then acknowledges and publishes the event. Queries, info and exports go through the
  same worker, so they see a consistent state between two operations; the worker takes them
  before the next queued write, so a flood of updates does not delay them.

Who may write what: the Zenoh access-control list (``deploy/``) lets a robot's identity send
requests only on its own ``update/<robot>`` and ``remove/<robot>`` keys; the server refuses an
update observed from (``a``), or creating (``b``), or a remove of, a frame outside that
namespace with ``Forbidden``. Zenoh gives a queryable nothing authenticated about the
requester (``Query.source_info`` is ``None`` unless the requester sets it, and then it is
whatever the requester says), so the key expression, which the ACL enforces, is the identity.
Every ack carries the server's Zenoh id; clients accept replies only from the server whose
liveliness token ``<prefix>/<map>/alive/<zid>`` they see.

Keys are listed in ``schemas/KEYS.md``. A failure part-way leaves the map as it was (the core
guarantees it); rejected inputs are answered with a typed error, logged, counted and not
recorded. If the recording itself fails the server stops (fail-stop: the recording must hold
every acknowledged input).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import zenoh

from mcsm import wire
from mcsm.errors import Busy, InternalError, McsmError, NotReplicated
from mcsm.log.replay import replay
from mcsm.log.topics import RecordingError, decode_input
from mcsm.log.writer import Recorder
from mcsm.map import ops
from mcsm.map.state import MapState
from mcsm.serve.connect import query_source, undeclare_all
from mcsm.serve.lanes import Full, Lanes
from mcsm.serve.options import ServerOptions, new_map, restore_summary

if TYPE_CHECKING:  # imported only by a server with --nats (mcsm.serve.replication needs nats-py)
    from mcsm.serve.replication import NatsLink, Replica

log = logging.getLogger(__name__)

_STOP = object()


@dataclass
class _Task:
    """Work for the worker that is not a client request (replication): ``run`` then ``done``."""

    run: Callable[[], Any]
    done: Callable[[], None] | None = None
    result: Any = None
    error: BaseException | None = None
    finished: threading.Event = field(default_factory=threading.Event)


@dataclass
class _Item:
    op: str
    state: MapState
    query: zenoh.Query
    key: str
    request: Any
    recv_ns: int
    payload: bytes
    sender: str
    namespace: str = ""


class Server:
    """An mcsm server on an open Zenoh session.

    Call :meth:`start` once, :meth:`close` once (also from a signal handler's thread).
    """

    def __init__(self, session: zenoh.Session, options: ServerOptions,
                 progress: Callable[[int, int], None] | None = None) -> None:
        self.session = session
        self.opts = options
        self.server_id = str(session.zid())
        self.states: dict[str, MapState] = {}
        self.keys: dict[str, wire.Keys] = {}
        self.recorder: Recorder | None = None
        self._queue = Lanes(options.queue_size, options.queue_bytes)
        self._entities: list[Any] = []
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._worker: threading.Thread | None = None
        self._progress = progress
        self._closed = False
        self._close_lock = threading.Lock()
        self.failed = threading.Event()  # set when the worker hit a fatal error
        self._reject_lock = threading.Lock()
        self.link: NatsLink | None = None  # --nats: the replicated log's connection
        self.replicas: dict[str, Replica] = {}  # replicated maps (primary or standby here)
        self._map_entities: dict[str, list[Any]] = {}  # a served map's queryable and token

    # ---------------------------------------------------------------- lifecycle
    def start(self) -> None:
        """Restore (if asked), open the recording, declare keys, start the worker.

        Raises
        ------
        RecordingError
            If the restore file diverges or cannot be read (the new recording is removed
            again), or the record path exists."""
        o = self.opts
        for name in [*o.maps, *o.standby_of]:
            wire.map_keys(name, o.prefix)  # check names before doing any work
        both = sorted(set(o.maps) & set(o.standby_of))
        if both:
            raise McsmError(f"map {both[0]!r} is both served and followed as a standby")
        if o.standby_of and o.nats is None:
            raise McsmError("--standby-of needs the map's log: add --nats URL (docs/fleet.md)")
        if o.standby_of and o.restore is not None:
            raise McsmError("a standby copies its state from the log: --standby-of "
                            "cannot be combined with --restore")
        if o.nats is None:  # a replicated map is refused by its lease (Replica.start)
            self.check_not_served(list(o.maps))
        restore = ([] if o.restore is None else
                   [Path(o.restore)] if isinstance(o.restore, (str, Path)) else list(o.restore))
        if o.record is not None:
            if any(Path(o.record).resolve() == p.resolve() for p in restore):
                raise RecordingError(str(o.record), "--record must differ from --restore "
                                     "(the restored server writes a new, self-contained file)")
            self.recorder = Recorder(o.record, fsync=o.fsync, split_bytes=o.split_bytes,
                                     split_s=o.split_s)
        if restore:
            try:
                rep = replay(restore, sink=self.recorder, from_snapshot=True,
                             progress=self._progress, lru_size=o.lru_size,
                             id_ttl_s=o.id_ttl_s, server_id=self.server_id, device=o.device)
                if rep.divergence is not None:
                    raise RecordingError(str(o.restore), f"replay diverged: {rep.divergence}")
            except (McsmError, OSError):
                if self.recorder is not None:  # it only holds a copy of the old file's prefix
                    self.recorder.close()
                    for p in self.recorder.paths:
                        p.unlink(missing_ok=True)
                raise
            self.states.update(rep.states)
            log.info("restored %d map(s) from %s (%s): %s", len(rep.states), o.restore,
                     "complete" if rep.complete else f"truncated: {rep.tail_error}",
                     restore_summary(rep))
            for st in self.states.values():
                st.id_ttl_s = o.id_ttl_s
                if self.recorder is not None:
                    self.recorder.checkpoint(st.name, st.seq, st.digest(), "restore")
        restored = set(self.states)
        maps = list(o.maps) or ([] if self.states or o.standby_of else [wire.DEFAULT_MAP])
        for name in maps:
            if name in self.states:
                if self.states[name].map.options() != new_map(o.map_options).options():
                    log.warning("map %r: using the restored options %s", name,
                                self.states[name].map.options())
                dfr = self.states[name].deferral
                if (None if dfr is None else dfr.options) != o.gate_defer:
                    log.warning("map %r: using the restored --gate-defer policy %s", name,
                                None if dfr is None else dfr.options.to_dict())
                continue
            st = MapState(name, new_map(o.map_options, o.device), o.lru_size,
                          o.id_ttl_s, snapshot_every=o.snapshot_every,
                          snapshots_kept=o.snapshots_kept, gate_defer=o.gate_defer,
                          retract_window_bytes=o.retract_window_bytes)
            self.states[name] = st
            if self.recorder is not None and o.nats is None:
                self.recorder.config(st, o.checkpoint_every, server_id=self.server_id)
        if o.nats is None:
            self.check_not_served([n for n in self.states if n not in o.maps])  # restored
        else:
            self._start_replicas(restored)
        self._worker = threading.Thread(target=self._run, name="mcsm-worker", daemon=True)
        self._worker.start()
        if o.nats is None:
            for name, st in self.states.items():
                self._declare(name, st)
            return
        for name, r in self.replicas.items():
            if r.claim and not r.promoted.wait(300.0):
                raise McsmError(f"map {name!r}: not serving within 300 s (its log: "
                                f"{r.stopped or 'not caught up'})")

    def _start_replicas(self, restored: set[str]) -> None:
        """--nats: connect; claim every served map (its lease, its log) and follow every
        --standby-of map; a claimed map whose log has inputs is built from the log."""
        from mcsm.serve.replication import NatsLink, Replica

        o = self.opts
        assert o.nats is not None
        self.link = NatsLink(o.nats, self.server_id)
        self.link.start()
        for name in list(self.states):
            r = Replica(self, self.link, name, wire.map_keys(name, o.prefix), claim=True,
                        state=self.states[name])
            r.start()
            self.replicas[name] = r
            st = r.st
            del self.states[name]  # served once promoted (the loop applies the log first)
            if st is None:
                continue  # its log has inputs: the replica builds the map from them
            if self.recorder is not None and name not in restored:
                self.recorder.config(st, o.checkpoint_every, server_id=self.server_id)
            r.recorded = st.seq if self.recorder is not None else -1
        for name in dict.fromkeys(o.standby_of):
            r = Replica(self, self.link, name, wire.map_keys(name, o.prefix), claim=False)
            r.start()
            self.replicas[name] = r

    def check_not_served(self, names: list[str], timeout_s: float = 2.0) -> None:
        """A server without ``--nats``: refuse maps another live server already serves (its
        liveliness token is seen), since two servers of one map would fork it. A replicated
        map is refused by its lease instead, and only by it (:meth:`Replica.start`): the
        token is the primary's address for clients, not a claim on the map.

        Raises
        ------
        McsmError
            Naming the map and the other server.
        """
        for name in names:
            k = wire.map_keys(name, self.opts.prefix)
            for reply in self.session.liveliness().get(k.alive_any, timeout=timeout_s):
                if reply.ok is None:
                    continue
                other = str(reply.ok.key_expr).rsplit("/", 1)[-1]
                if other != self.server_id:
                    raise McsmError(f"map {name!r} is already served by server {other} "
                                    f"(liveliness token {reply.ok.key_expr}): refusing to "
                                    "serve it a second time (to follow it, start this "
                                    f"server with --standby-of {name})")

    def _declare(self, name: str, st: MapState) -> None:
        k = wire.map_keys(name, self.opts.prefix)
        self.keys[name] = k
        s = self.session
        # One queryable per map: one callback thread, one arrival order for all its keys.
        ents = [s.declare_queryable(k.all, lambda query: self._on_query(k, st, query),
                                    complete=False),
                s.liveliness().declare_token(k.alive(self.server_id))]
        self._map_entities[name] = ents
        self._entities.extend(ents)
        self._publishers[name] = s.declare_publisher(k.events, express=True,
                                                     encoding=wire.ENCODING)
        log.info("serving map %r on %s (N=%d, seq=%d)", name, k.all, st.n_samples, st.seq)

    def close(self) -> None:
        """Stop taking requests, answer those queued, write final checkpoints, close the file."""
        with self._close_lock:
            if self._closed:
                return
            self._closed = True
        # No new requests; the liveliness tokens stay while the worker answers the queued
        # ones (a client cancels its request when the server's token goes away, and would
        # ask again elsewhere what this server is applying) and go before the lease is
        # released (a client never sees two servers claim the map).
        ents, self._entities = self._entities, []
        tokens = [e for e in ents if isinstance(e, zenoh.LivelinessToken)]
        undeclare_all([e for e in ents if not isinstance(e, zenoh.LivelinessToken)])
        for r in self.replicas.values():
            r.stop_loop()
        if self._worker is not None and self._worker.is_alive():
            self._queue.put(_STOP, force=True)
            self._worker.join(timeout=60.0)
            if self._worker.is_alive():
                log.error("worker did not stop within 60 s")
        undeclare_all(tokens)
        for r in self.replicas.values():  # a primary's lease is released: a standby takes over
            r.close(release=True)
        if self.link is not None:
            self.link.close()
        undeclare_all(list(self._publishers.values()))
        if self.recorder is not None and not self.recorder.closed:
            try:
                if not self.failed.is_set():
                    for st in self.states.values():
                        self.recorder.checkpoint(st.name, st.seq, st.digest(), "close")
                    for r in self.replicas.values():
                        if r.st is not None and r.role == "standby" and not r.dirty:
                            self.recorder.checkpoint(r.name, r.st.seq, r.st.digest(), "close")
                self.recorder.close()
                log.info("recording closed: %s (%d inputs)", self.recorder.path,
                         self.recorder.n_inputs)
            except (OSError, ValueError) as exc:  # a full disk: the file stays cut, complete
                self.recorder.closed = True       # up to its last record
                self.failed.set()
                log.critical("could not close the recording %s cleanly: %s; it ends after its "
                             "last complete record (mcsm recover indexes it)",
                             self.recorder.path, exc)

    # ---------------------------------------------------------------- zenoh callbacks
    def _on_query(self, k: wire.Keys, st: MapState, query: zenoh.Query) -> None:
        """Route, decode, check and enqueue; never touches the map (runs on Zenoh's thread
        of this map's queryable, one query at a time, in arrival order)."""
        recv_ns = time.time_ns()
        key = str(query.key_expr)
        op = "request"
        try:
            leaf, ns = k.route(key)
            op = leaf
            payload = query.payload.to_bytes() if query.payload is not None else b""
            operation, req = ops.decode_request(leaf, payload, st.n_samples)
            op = operation.name
            operation.check_namespace(req, ns, key)
        except McsmError as exc:
            self._reject(st, query, exc, "", op)
            query.drop()
            return
        sender = getattr(req, "sender", "") or query_source(query)
        item = _Item(op, st, query, key, req, recv_ns, payload, sender, ns)
        try:
            self._queue.put(item, len(payload), read=not operation.changes_state)
        except Full as full:
            self._reject(st, query, Busy(full.value, full.limit, full.what),
                         getattr(req, "request_id", ""), op)
            query.drop()

    def _reject(self, st: MapState, query: zenoh.Query, err: McsmError, request_id: str,
                op: str) -> None:
        with self._reject_lock:
            st.count_rejected(err)
        log.info("rejected %s on map %r: %s: %s", op, st.name, type(err).__name__, err)
        try:
            query.reply_err(wire.encode_error(err, request_id), encoding=wire.ENCODING)
        except zenoh.ZError as exc:
            log.warning("could not send an error reply: %s", exc)

    # ---------------------------------------------------------------- the worker
    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                continue
            if item is _STOP:
                return
            if isinstance(item, _Task):
                self._run_task(item)
                continue
            try:
                self._handle(item)
            except Exception:  # the outermost loop: log, answer, keep serving
                log.exception("internal error on %s", item.op)
                self._reply_err(item, InternalError("see the server log"))
            finally:
                item.query.drop()

    def _run_task(self, task: _Task) -> None:
        try:
            task.result = task.run()
        except Exception as exc:  # logged; the caller that waits gets it back
            log.exception("replication task")
            task.error = exc
        finally:
            task.finished.set()
            if task.done is not None:
                task.done()

    def submit(self, run: Callable[[], Any], done: Callable[[], None] | None = None) -> bool:
        """Queue ``run`` (then ``done``) for the worker; False if the queue is full."""
        try:
            self._queue.put(_Task(run, done))
        except Full:
            return False
        return True

    def run_in_worker(self, run: Callable[[], Any], timeout_s: float) -> Any:
        """Run ``run`` on the worker (between two operations) and return its result.

        Raises
        ------
        McsmError
            If the worker did not run it within ``timeout_s`` (or it raised).
        """
        task = _Task(run)
        self._queue.put(task, force=True)  # the server's own work: never refused
        if not task.finished.wait(timeout_s):
            raise McsmError(f"the worker did not get to it within {timeout_s:g} s")
        if task.error is not None:
            raise McsmError(f"failed on the worker: {task.error}") from task.error
        return task.result

    def promote(self, r: Replica) -> bool:
        """On the worker: ``r``'s server holds the lease and applied the whole log: serve
        the map (declare its keys) and acknowledge from now on."""
        from mcsm.serve.replication import TAKEOVER

        st = r.st
        if self._closed or st is None or r.dirty or r.stopped is not None or not r.lease.holding:
            return False
        r.role = "primary"
        self.states[st.name] = st
        self._declare(st.name, st)
        first = r.claim and r.takeovers == 0
        r.takeovers += 1
        r.promoted.set()
        if first:
            return True
        digest = st.digest()
        if self.recorder is not None:
            try:
                self.recorder.checkpoint(st.name, st.seq, digest, "takeover")
            except (OSError, ValueError) as exc:
                log.critical("recording failed: %s", exc)
                self.failed.set()
        took = time.monotonic() - r.lost_at if r.lost_at is not None else float("nan")
        log.warning("map %r: took over as primary at seq %d (lease revision %d)", st.name,
                    st.seq, r.term)
        ev = wire.Event(map=st.name, seq=st.seq, op=TAKEOVER, kind=TAKEOVER, frames=(),
                        component=None, time_ns=time.time_ns(), digest=digest,
                        extra={"server": self.server_id, "takeover_s": took})
        try:
            self._publishers[st.name].put(wire.encode_event(ev))
        except zenoh.ZError as exc:
            log.warning("could not publish the takeover event: %s", exc)
        return True

    @property
    def recording_path(self) -> str:
        """The recording file written now (``-`` without one)."""
        return str(self.recorder.path) if self.recorder is not None else "-"

    def demote(self, r: Replica, why: str) -> None:
        """On the worker: stop serving ``r``'s map (the lease is lost, or the log refused an
        input); the replica follows the log again (after a rebuild if its state is dirty)."""
        name = r.name
        if r.role != "primary":
            return
        r.role = "standby"
        r.promoted.clear()
        r.lost_at = time.monotonic()
        log.warning("map %r: not serving it any more: %s", name, why)
        ents = self._map_entities.pop(name, [])
        undeclare_all(list(ents))
        self._entities[:] = [e for e in self._entities if all(e is not x for x in ents)]
        pub = self._publishers.pop(name, None)
        if pub is not None:
            undeclare_all([pub])
        st = self.states.pop(name, None)
        if st is not None and not r.dirty and self.recorder is not None \
                and not self.failed.is_set():
            try:
                self.recorder.checkpoint(name, st.seq, st.digest(), "deposed")
            except (OSError, ValueError) as exc:
                log.critical("recording failed: %s", exc)
                self.failed.set()

    @property
    def closed(self) -> bool:
        return self._closed

    def _reply(self, item: _Item, payload: bytes) -> None:
        try:
            item.query.reply(item.key, payload, express=True, encoding=wire.ENCODING)
        except zenoh.ZError as exc:
            log.warning("could not reply to %s: %s", item.op, exc)

    def _reply_err(self, item: _Item, err: McsmError) -> None:
        try:
            item.query.reply_err(wire.encode_error(err, getattr(item.request, "request_id", "")),
                                 encoding=wire.ENCODING)
        except zenoh.ZError as exc:
            log.warning("could not send an error reply: %s", exc)

    def _handle(self, item: _Item) -> None:
        st = item.state
        if self.states.get(st.name) is not st:
            self._reply_err(item, NotReplicated(st.name, "this server does not serve it now "
                                                "(another server holds its lease)"))
            return
        if self.failed.is_set():
            self._reply_err(item, McsmError("server stopped: recording failed"))
            return
        operation = ops.get(item.op)
        if operation.changes_state:
            self._apply(item)
            return
        if operation.answer is None:
            raise McsmError(f"operation {item.op!r} has no answer")
        try:
            payload = operation.answer(self, st, item.request)
        except McsmError as exc:
            self._reject(st, item.query, exc, getattr(item.request, "request_id", ""), item.op)
            return
        self._reply(item, payload)

    def _apply(self, item: _Item) -> None:
        st, req = item.state, item.request
        operation = ops.get(item.op)
        fingerprint = ops.fingerprint(item.op, req)
        try:
            dup = st.lookup(req.request_id, fingerprint, item.recv_ns)
        except McsmError as exc:  # RequestIdReused: an id sent again with another request
            self._reject(st, item.query, exc, req.request_id, item.op)
            return
        rep = self.replicas.get(st.name)
        if rep is not None and not rep.may_ack():
            self._reject(st, item.query, NotReplicated(
                st.name, "this server does not hold the map's lease now"), req.request_id,
                item.op)
            return
        if dup is not None:
            log.info("map %r: request %s already applied as seq %d; resending its ack",
                     st.name, req.request_id, dup.seq)
            self._reply(item, wire.encode_ack(replace(dup, server=self.server_id)))
            return
        try:
            operation.check_namespace_map(st, req, item.namespace, item.key)
            ack = st.apply(item.op, req, time_ns=item.recv_ns, fingerprint=fingerprint,
                           payload=item.payload)
        except McsmError as exc:
            self._reject(st, item.query, exc, req.request_id, item.op)
            return
        ack = replace(ack, server=self.server_id)
        digest = st.digest() if ack.seq % self.opts.checkpoint_every == 0 else None
        if rep is not None:
            from mcsm.serve.replication import Entry, Refused

            try:
                rep.append(Entry(ack.seq, item.op, item.recv_ns, item.sender, req.request_id,
                                 item.payload, digest))
            except Refused as exc:
                log.warning("map %r: the log refused seq %d: %s", st.name, ack.seq, exc)
                self.demote(rep, f"the log refused seq {ack.seq}: {exc}")
                self._reply_err(item, NotReplicated(st.name, f"the log did not take it ({exc})"))
                return
        try:
            if self.recorder is not None:
                self.recorder.input(item.op, st.name, ack.seq, item.recv_ns, item.sender,
                                    req.request_id, item.payload)
                if digest is not None:
                    self.recorder.checkpoint(st.name, ack.seq, digest, "periodic")
                k = self.opts.disk_snapshot_every
                if k > 0 and ack.seq % k == 0:
                    self.recorder.snapshot(st)
        except (OSError, ValueError, RecordingError) as exc:
            # The map holds an input the file does not: stop rather than acknowledge it.
            log.critical("recording failed at seq %d of map %r: %s; stopping", ack.seq,
                         st.name, exc)
            self.failed.set()
            self._reply_err(item, McsmError(f"recording failed: {exc}"))
            return
        if rep is not None:
            if self.recorder is not None:
                rep.recorded = ack.seq
            if rep.disk_snapshot_every and ack.seq % rep.disk_snapshot_every == 0:
                rep.snapshot_soon()
        if rep is None or rep.may_ack():
            self._reply(item, wire.encode_ack(ack))
        else:  # in the log and recorded; the retry is acknowledged by the lease's holder
            self._reply_err(item, NotReplicated(st.name, "the lease may have expired while "
                                                "the log stored it"))
        ev = ops.event(item.op, st, req, ack, time_ns=time.time_ns(), digest=digest)
        try:
            self._publishers[st.name].put(wire.encode_event(ev))
        except zenoh.ZError as exc:
            log.warning("could not publish event %d: %s", ack.seq, exc)

    def info(self, st: MapState) -> wire.MapInfo:
        """The info reply of one map (call from the worker, or when nothing else runs)."""
        m = st.map
        rep = self.replicas.get(st.name)
        mem = m.memory()
        with self._reject_lock:
            rejected, by_error = st.rejected, dict(st.rejected_by_error)
        return wire.MapInfo(
            map=st.name, n_samples=st.n_samples, options=m.options(), seq=st.seq,
            digest=st.digest(), frames=tuple(m.frames()),
            components={r: tuple(m.component(r)) for r in m.components()},
            rejected=rejected, rejected_by_error=by_error, server_id=self.server_id,
            verdicts=dict(st.verdicts),
            recording=str(self.recorder.path) if self.recorder is not None else "",
            queue_length=self._queue.qsize(),
            standbys=dict(rep.standbys) if rep is not None else {},
            replicas=self.link.opts.replicas if self.link is not None else 0,
            epoch=rep.term if rep is not None else 0,
            device=m.device, device_bytes=mem["bytes"], device_free_bytes=mem.get("free", 0))


__all__ = ["Server", "ServerOptions", "decode_input", "new_map", "restore_summary",
           "undeclare_all"]
