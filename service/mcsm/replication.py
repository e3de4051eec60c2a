"""Hot standbys: a map's inputs, in sequence order, on other server processes.

Roles. For each map, one server is the *primary*: it declares the map's queryable and the
liveliness token ``<prefix>/<map>/alive/<zid>`` that clients look for. Servers started with
``mcsm serve --standby-of MAP`` are *standbys* of that map: each declares the queryable and
liveliness token ``<prefix>/<map>/@standby/<zid>`` (a verbatim ``@`` chunk, so the map's
``**`` queryable never sees replication traffic) and watches the primary's token.

The stream (:class:`PrimaryLink`). After the primary has applied and recorded an input, and
before it acknowledges it, it pushes the input's recording record (seq, operation, receive
time, sender, request id, request bytes, and the digest at checkpoints) to every standby. A
standby (:class:`Follower`) applies it through :meth:`MapState.apply` exactly as replay does,
records it in its own MCAP, and compares digests at the primary's checkpoints (a mismatch stops
that standby: it never takes over with a forked map). With ``--sync-standbys K`` the primary
acknowledges an update only once K standbys confirmed they hold it, and refuses writes (with the
retryable :class:`~mcsm.errors.NotReplicated`) while fewer than K standbys are alive; without
it (K = 0) the push is fire-and-forget, and what the primary acknowledged in the last moments
before it died (the pushes still in flight, typically the last few milliseconds) can be lost.

Catch-up. A standby that starts late or sees a gap in the seqs asks the primary's
``<prefix>/<map>/@log`` queryable for the inputs after its seq: the primary answers from its
in-memory log of the last ``--repl-log`` inputs, or, if the standby is further behind, with a
snapshot of the map (taken on the primary's worker, sent in parts below the message cap, with
the remembered request ids) followed by the inputs after it. A standby that already holds a
state and falls behind the log stops (its recording could not continue): restart it.

Takeover. When the primary's liveliness token disappears, every standby asks the others for
their seq (through the worker, after the inputs already queued) and the one with the highest
seq, ties broken by the smallest server id, becomes primary: it checks that no other server
declared the map meanwhile, declares the map's keys, records a ``takeover`` checkpoint,
announces a ``takeover`` event and continues the seq. The others follow the new primary's token.
Every standby computes the same choice from the same answers, so there is one winner as long as
the standbys see each other; across a network partition two could promote, and the later one
then refuses if it sees the first one's token (Zenoh liveliness is not a consensus protocol).
A returning old primary is started again with ``--standby-of`` and a new recording: it catches up
from the new primary.
"""

from __future__ import annotations

import functools
import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import zenoh

from mcsm import wire
from mcsm.core.smap import StochasticMap
from mcsm.errors import BadMessage, McsmError, NotReplicated
from mcsm.log.topics import INPUT_TOPICS, decode_input
from mcsm.map.carry import decode_snapshot, encode_snapshot
from mcsm.map.deferral import DeferOptions, DeferState
from mcsm.map.state import MapState

if TYPE_CHECKING:
    from mcsm.server import Server

log = logging.getLogger(__name__)

PART_BYTES = 4 * 1024 * 1024
"""Bytes of a snapshot per catch-up reply (below the servers' 8 MiB message cap)."""
BATCH_BYTES = 4 * 1024 * 1024
"""Bytes of inputs per catch-up reply."""
DEFAULT_LOG_ENTRIES = 2000
"""Inputs the primary keeps in memory for standbys that catch up (``--repl-log``)."""
DEFAULT_SYNC_TIMEOUT_S = 2.0
"""How long the primary waits for its synchronous standbys' confirmation of one input."""
_MAX_MSG = 64 * 1024 * 1024
SETTLE_S = 0.0
"""How long a standby waits, after its primary's token went away, before it checks that it
still reaches a router or peer. Zero: a lost router's link is gone from the session before
the tokens it carried are withdrawn (20 of 20 router restarts under load, two at a time:
``test_a_router_restart_does_not_split_the_map``)."""
TAKEOVER = "takeover"
"""The event (``op`` and ``kind``) a standby publishes when it becomes the map's primary."""


# --------------------------------------------------------------------------------- messages
@dataclass(frozen=True)
class Entry:
    """One applied input as the primary recorded it."""

    seq: int
    op: str
    recv_ns: int
    sender: str
    request_id: str
    payload: bytes
    digest: str | None = None

    def to_obj(self) -> dict[str, Any]:
        return {"seq": self.seq, "op": self.op, "recv_ns": self.recv_ns, "sender": self.sender,
                "id": self.request_id, "request": self.payload, "digest": self.digest}

    @staticmethod
    def from_obj(obj: Any) -> Entry:
        """Checked inverse of :meth:`to_obj`.

        Raises
        ------
        BadMessage
            If a field is missing or of the wrong type.
        """
        if not isinstance(obj, dict):
            raise BadMessage("entry", "a map", type(obj).__name__)
        seq, op, recv = obj.get("seq"), obj.get("op"), obj.get("recv_ns")
        sender, rid, req, dig = (obj.get("sender"), obj.get("id"), obj.get("request"),
                                 obj.get("digest"))
        if type(seq) is not int or seq < 1 or type(recv) is not int:
            raise BadMessage("entry.seq/recv_ns", "integers", f"{seq!r}, {recv!r}")
        if op not in INPUT_TOPICS:
            raise BadMessage("entry.op", f"one of {sorted(INPUT_TOPICS)}", repr(op)[:40])
        if not isinstance(sender, str) or not isinstance(rid, str) \
                or not isinstance(req, bytes) or not (dig is None or isinstance(dig, str)):
            raise BadMessage("entry", "sender, id: str; request: bytes; digest: str or nil",
                             "other types")
        return Entry(seq, str(op), recv, sender, rid, req, dig)


def _pack(obj: dict[str, Any]) -> bytes:
    return wire.pack({"v": wire.VERSION, **obj})


def _unpack(payload: bytes) -> dict[str, Any]:
    return wire.unpack(payload, max_bytes=_MAX_MSG, max_map_len=1 << 20)


def undeclare_all(entities: list[Any]) -> None:
    """Undeclare Zenoh entities (queryables, tokens, subscribers, publishers) and empty the
    list; an entity the session already dropped is only logged."""
    for ent in entities:
        try:
            ent.undeclare()
        except zenoh.ZError as exc:
            log.debug("undeclare: %s", exc)
    entities.clear()


def _zid_of(key: Any) -> str:
    return str(key).rsplit("/", 1)[-1]


# ------------------------------------------------------------------------------ the primary
class ReplLog:
    """The last inputs of one map, for standbys that catch up (thread-safe)."""

    def __init__(self, head: int, max_entries: int) -> None:
        self._lock = threading.Lock()
        self._entries: deque[Entry] = deque()
        self.head = int(head)
        self.max_entries = max(1, int(max_entries))
        self._snapshot: tuple[int, bytes] | None = None

    def append(self, e: Entry) -> None:
        with self._lock:
            if self._entries and e.seq != self._entries[-1].seq + 1:
                self._entries.clear()  # not contiguous (cannot happen in one worker): restart
            self._entries.append(e)
            while len(self._entries) > self.max_entries:
                self._entries.popleft()
            self.head = e.seq

    def latest(self) -> Entry | None:
        with self._lock:
            return self._entries[-1] if self._entries else None

    def since(self, seq: int, max_bytes: int = BATCH_BYTES) -> list[Entry] | None:
        """The inputs after ``seq`` (at most ``max_bytes`` of them, at least one), or None if
        the log no longer reaches back to ``seq + 1`` (a snapshot is needed)."""
        with self._lock:
            if seq >= self.head:
                return []
            if not self._entries or self._entries[0].seq > seq + 1:
                return None
            out: list[Entry] = []
            size = 0
            start = seq + 1 - self._entries[0].seq
            for k in range(start, len(self._entries)):
                e = self._entries[k]
                if out and size + len(e.payload) > max_bytes:
                    break
                out.append(e)
                size += len(e.payload) + 200
            return out

    def snapshot(self, seq: int | None = None) -> tuple[int, bytes] | None:
        """The cached snapshot (of ``seq`` if given) if the log still continues it."""
        with self._lock:
            s = self._snapshot
            if s is None or (seq is not None and s[0] != seq):
                return None
            if s[0] < self.head and (not self._entries or self._entries[0].seq > s[0] + 1):
                return None
            return s

    def keep_snapshot(self, seq: int, blob: bytes) -> None:
        with self._lock:
            self._snapshot = (int(seq), blob)


class PrimaryLink:
    """The primary's side of one map's replication: the log, the pushes, the catch-up
    queryable and the standbys it sees (their liveliness tokens and confirmed seqs)."""

    def __init__(self, server: Server, st: MapState, keys: wire.Keys,
                 recent: list[Entry] | None = None, sync: int = 0, epoch: int = 0) -> None:
        o = server.opts
        self.server, self.st, self.keys = server, st, keys
        self.epoch = int(epoch)
        """How many takeovers made this primary (0: started with --map). Two primaries that
        meet (one was cut off while a standby took over) keep the higher epoch's (then the
        smaller id's) and the other steps down."""
        self.sync = max(0, int(o.sync_standbys), int(sync))
        self.timeout_s = float(o.sync_timeout_s)
        self.log = ReplLog(st.seq - len(recent or []), o.repl_log)
        for e in recent or []:  # a promoted standby's last inputs: the others catch up from it
            self.log.append(e)
        self.confirmed = st.seq  # acknowledged inputs before this link are not its business
        self._lock = threading.Lock()
        self._standbys: dict[str, int] = {}  # zid -> last seq it confirmed (-1: none yet)
        self._config = {"options": st.map.options(), "n_samples": st.n_samples,
                        "checkpoint_every": o.checkpoint_every, "sync_standbys": self.sync,
                        "epoch": self.epoch,
                        "disk_snapshot_every": o.disk_snapshot_every,
                        "snapshot_every": st.history.snapshot_every,
                        "snapshots_kept": st.history.snapshots_kept,
                        "retract_window_bytes": st.history.max_bytes,
                        "gate_defer": (None if st.deferral is None
                                       else st.deferral.options.to_dict())}
        s = server.session
        self._entities: list[Any] = [
            s.liveliness().declare_subscriber(keys.standby_any, self._on_token, history=True),
            s.declare_queryable(keys.log, self._on_log, complete=True),
            s.liveliness().declare_subscriber(keys.alive_any, self._on_primary),
        ]

    def close(self) -> None:
        undeclare_all(self._entities)

    # ---------------------------------------------------------------- standbys
    def _on_token(self, sample: zenoh.Sample) -> None:
        zid = _zid_of(sample.key_expr)
        if zid == self.server.server_id:
            return  # this server's own token as a standby, before it took over
        with self._lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self._standbys.setdefault(zid, -1)
                log.info("map %r: standby %s joined", self.st.name, zid)
            else:
                self._standbys.pop(zid, None)
                log.info("map %r: standby %s left", self.st.name, zid)

    def _on_primary(self, sample: zenoh.Sample) -> None:
        """Another primary of this map appeared (this server was cut off and a standby took
        over, or two standbys promoted across a partition): settle it off Zenoh's thread."""
        zid = _zid_of(sample.key_expr)
        if sample.kind == zenoh.SampleKind.PUT and zid != self.server.server_id:
            threading.Thread(target=self._contest, args=(zid,), daemon=True,
                             name=f"mcsm-contest-{self.st.name}").start()

    def _contest(self, other: str) -> None:
        """Step down if ``other`` has the higher epoch (or the same and a smaller id)."""
        try:
            self._settle(other)
        except (zenoh.ZError, McsmError) as exc:  # the session or the worker closed meanwhile
            log.info("map %r: not settled with %s: %s", self.st.name, other, exc)

    def _settle(self, other: str) -> None:
        epoch = None
        for _ in range(10):  # its info, a few tries while it is coming up
            for reply in self.server.session.get(self.keys.info, timeout=2.0,
                                                 target=zenoh.QueryTarget.ALL,
                                                 consolidation=zenoh.ConsolidationMode.NONE):
                rid = str(reply.replier_id.zid) if reply.replier_id is not None else ""
                if rid == other and reply.ok is not None:
                    try:
                        epoch = wire.decode_info_reply(reply.ok.payload.to_bytes()).epoch
                    except McsmError:
                        continue
            if epoch is not None or self.server.closed:
                break
            time.sleep(0.2)
        if epoch is None:
            log.warning("map %r: another primary %s appeared but did not answer info",
                        self.st.name, other)
            return
        if epoch > self.epoch or (epoch == self.epoch and other < self.server.server_id):
            why = (f"server {other} serves it too with epoch {epoch} (this server: epoch "
                   f"{self.epoch}): this server was cut off while a standby took over")
            self.server.run_in_worker(lambda: self.server.step_down(self.st.name, why),
                                      timeout_s=60.0)
        else:
            log.warning("map %r: server %s serves it too (epoch %d); it steps down (this "
                        "server: epoch %d)", self.st.name, other, epoch, self.epoch)

    def standbys(self) -> dict[str, int]:
        """Live standbys and the last seq each confirmed (0 if none yet)."""
        with self._lock:
            return {z: max(0, s) for z, s in self._standbys.items()}

    def can_accept(self) -> bool:
        """Whether enough standbys are alive to acknowledge a new update."""
        with self._lock:
            return len(self._standbys) >= self.sync

    def refusal(self, reason: str) -> NotReplicated:
        with self._lock:
            have = len(self._standbys)
        return NotReplicated(self.st.name, have, self.sync, reason)

    def _note(self, reply: zenoh.Reply) -> tuple[str, int] | None:
        """The (standby, seq it holds) of a push reply, recorded; None if not a confirmation."""
        if reply.ok is None:
            return None
        try:
            d = _unpack(reply.ok.payload.to_bytes())
            zid, seq = str(d["zid"]), int(d["seq"])
        except (McsmError, KeyError, TypeError, ValueError):
            return None
        with self._lock:
            if zid in self._standbys:
                self._standbys[zid] = max(self._standbys[zid], seq)
        return zid, seq

    # ---------------------------------------------------------------- pushes (worker)
    def push(self, e: Entry) -> bool:
        """Log ``e`` and send it to the standbys; True when ``sync`` of them hold it."""
        self.log.append(e)
        return self._send(e)

    def ensure(self, seq: int) -> bool:
        """For a retried request applied as ``seq``: True once ``sync`` standbys hold it
        (the latest input is pushed again; a standby that is behind catches up)."""
        if self.sync == 0 or seq <= self.confirmed:
            return True
        e = self.log.latest()
        return e is not None and self._send(e)

    def _send(self, e: Entry) -> bool:
        with self._lock:
            n = len(self._standbys)
        if n == 0:
            return self.sync == 0
        payload = _pack({"t": "push", "primary": self.server.server_id, "epoch": self.epoch,
                         "entry": e.to_obj()})
        kw: dict[str, Any] = {"payload": payload, "target": zenoh.QueryTarget.ALL,
                              "consolidation": zenoh.ConsolidationMode.NONE,
                              "congestion_control": zenoh.CongestionControl.BLOCK,
                              "timeout": self.timeout_s}
        if self.sync == 0:
            self.server.session.get(self.keys.standby_any, handler=self._note_async, **kw)
            return True
        # every reply is noted (the lag of each standby in info), but the worker waits only
        # for the first ``sync`` confirmations, or for the query's end (all replied, timeout)
        have: set[str] = set()
        wake = threading.Event()

        def on_reply(reply: zenoh.Reply) -> None:
            got = self._note(reply)
            if got is not None and got[1] >= e.seq:
                have.add(got[0])
                if len(have) >= self.sync:
                    wake.set()

        self.server.session.get(self.keys.standby_any, **kw, handler=zenoh.handlers.Callback(
            on_reply, wake.set, indirect=False))
        wake.wait(self.timeout_s + 1.0)
        if len(have) >= self.sync:
            self.confirmed = max(self.confirmed, e.seq)
            return True
        log.warning("map %r: seq %d confirmed by %d of %d synchronous standbys within %.3g s",
                    self.st.name, e.seq, len(have), self.sync, self.timeout_s)
        return False

    def _note_async(self, reply: zenoh.Reply) -> None:
        self._note(reply)

    # ---------------------------------------------------------------- catch-up (zenoh thread)
    def _on_log(self, query: zenoh.Query) -> None:
        try:
            req = _unpack(query.payload.to_bytes() if query.payload is not None else b"")
            body = self._catch_up(req)
            query.reply(self.keys.log, _pack(body), encoding=wire.ENCODING)
        except McsmError as exc:
            query.reply_err(wire.encode_error(exc), encoding=wire.ENCODING)
        except Exception:  # a standby's request must never kill the primary's thread
            log.exception("catch-up request")
            query.reply_err(wire.encode_error(McsmError("internal error")),
                            encoding=wire.ENCODING)
        finally:
            query.drop()

    def _catch_up(self, req: dict[str, Any]) -> dict[str, Any]:
        base = {"config": self._config, "primary": self.server.server_id}
        part = req.get("snapshot")
        if part is not None:  # [seq, offset] of a snapshot being downloaded
            seq, offset = int(part[0]), int(part[1])
            snap = self.log.snapshot(seq)
            if snap is None:
                raise McsmError(f"snapshot {seq} is gone; ask again")
            return {**base, "snapshot": self._part(snap, offset), "head": self.log.head}
        have = int(req.get("from", -1))  # -1: a new standby (it starts from the empty map)
        entries = self.log.since(max(0, have))
        if entries is not None:
            return {**base, "entries": [e.to_obj() for e in entries], "head": self.log.head}
        snap = self.log.snapshot()
        if snap is None:
            snap = self.server.run_in_worker(self._take_snapshot, timeout_s=120.0)
        return {**base, "snapshot": self._part(snap, 0), "head": self.log.head}

    @staticmethod
    def _part(snap: tuple[int, bytes], offset: int) -> dict[str, Any]:
        seq, blob = snap
        return {"seq": seq, "size": len(blob), "offset": offset,
                "part": blob[offset:offset + PART_BYTES]}

    def _take_snapshot(self) -> tuple[int, bytes]:
        st = self.st
        blob = _pack({"seq": st.seq, "digest": st.digest(), "verdicts": dict(st.verdicts),
                      "state": encode_snapshot(st.map.snapshot()), "ids": st.export_ids(),
                      "deferral": None if st.deferral is None else st.deferral.state.encode()})
        self.log.keep_snapshot(st.seq, blob)
        return st.seq, blob


# ------------------------------------------------------------------------------ a standby
class Follower:
    """A standby of one map: applies the primary's stream, catches up, takes over."""

    def __init__(self, server: Server, name: str, keys: wire.Keys) -> None:
        self.server, self.name, self.keys = server, name, keys
        self.st: MapState | None = None
        self.checkpoint_every = 100
        self.sync = 0  # the primary's --sync-standbys: kept when this standby takes over
        self.epoch = 0  # the primary's epoch: this standby takes over with the next one
        self.disk_snapshot_every = 0
        self.primary: str | None = None
        self.stopped: str | None = None  # why this standby stopped following (never promoted)
        self.promoted = False
        self._need = threading.Event()
        self._primary_seen = threading.Event()
        self._stop = threading.Event()
        self._elections = 0
        self.lost_at: float | None = None  # monotonic time the primary's token went away
        self.recent: deque[Entry] = deque(maxlen=max(1, int(server.opts.repl_log)))
        s = server.session
        zid = server.server_id
        self._entities: list[Any] = [
            s.declare_queryable(keys.standby(zid), self._on_query, complete=True),
            s.liveliness().declare_token(keys.standby(zid)),
            s.liveliness().declare_subscriber(keys.alive_any, self._on_alive, history=True),
        ]
        self._thread = threading.Thread(target=self._loop, name=f"mcsm-standby-{name}",
                                        daemon=True)
        self._need.set()
        self._thread.start()
        log.info("standby of map %r (server %s)", name, zid)

    def close(self) -> None:
        self._stop.set()
        self._undeclare()
        if self._thread.is_alive() and threading.current_thread() is not self._thread:
            self._thread.join(timeout=10.0)

    def _undeclare(self) -> None:
        undeclare_all(self._entities)

    @property
    def seq(self) -> int:
        return self.st.seq if self.st is not None else -1

    # ---------------------------------------------------------------- zenoh callbacks
    def _on_alive(self, sample: zenoh.Sample) -> None:
        zid = _zid_of(sample.key_expr)
        if zid == self.server.server_id:
            return
        if sample.kind == zenoh.SampleKind.PUT:
            self.primary = zid
            self.lost_at = None
            self._primary_seen.set()
            self._need.set()
            log.info("map %r: following primary %s", self.name, zid)
        elif zid == self.primary:
            self.primary = None
            self.lost_at = time.monotonic()
            self._primary_seen.clear()
            log.warning("map %r: primary %s is gone", self.name, zid)
            threading.Thread(target=self._elect, args=(zid,), name=f"mcsm-elect-{self.name}",
                             daemon=True).start()

    def _on_query(self, query: zenoh.Query) -> None:
        """A push or a status request: both answered by the worker, in arrival order."""
        try:
            d = _unpack(query.payload.to_bytes() if query.payload is not None else b"")
            kind = d.get("t")
            if kind == "push":
                e = Entry.from_obj(d.get("entry"))
                sender = str(d.get("primary", ""))
                epoch = d.get("epoch", 0)
                if type(epoch) is not int or epoch < 0:
                    raise BadMessage("epoch", "an integer >= 0", repr(epoch)[:40])
                task: Callable[[], None] = lambda: self._reply_push(  # noqa: E731
                    query, e, sender, epoch)
            elif kind == "status":
                task = lambda: self._reply(query, {"t": "status"})  # noqa: E731
            else:
                raise BadMessage("t", "push or status", repr(kind)[:40])
        except McsmError as exc:
            query.reply_err(wire.encode_error(exc), encoding=wire.ENCODING)
            query.drop()
            return
        if not self.server.submit(task, lambda: query.drop()):
            query.reply_err(wire.encode_error(McsmError("standby queue full")),
                            encoding=wire.ENCODING)
            query.drop()

    def _reply(self, query: zenoh.Query, extra: dict[str, Any]) -> None:
        ok = self.st is not None and self.stopped is None and not self.promoted
        body = {**extra, "zid": self.server.server_id, "seq": self.seq if ok else -1}
        try:
            query.reply(query.key_expr, _pack(body), encoding=wire.ENCODING)
        except zenoh.ZError as exc:
            log.debug("standby reply: %s", exc)

    # ---------------------------------------------------------------- the worker
    def _reply_push(self, query: zenoh.Query, e: Entry, sender: str, epoch: int) -> None:
        if self.promoted or self.stopped is not None:
            pass
        elif sender != self.primary:  # not (yet) the server whose token this standby sees
            log.warning("map %r: ignoring a push from %r (following %s)", self.name, sender,
                        self.primary)
        else:
            self.epoch = epoch  # a takeover by this standby is the next epoch
            if self.st is None or e.seq > self.st.seq + 1:
                self._need.set()
            elif e.seq == self.st.seq + 1:
                self._apply(e)
            elif not self._same(e):
                self._stop_following(f"seq {e.seq} here is another input than the primary's "
                                     f"({e.request_id!r}): the histories forked")
        self._reply(query, {"t": "have"})

    def _same(self, e: Entry) -> bool:
        """Whether the input this standby holds at ``e.seq`` is ``e`` (True if too old to
        tell: only the last ``--repl-log`` inputs are kept)."""
        k = e.seq - self.recent[0].seq if self.recent else -1
        if not 0 <= k < len(self.recent):
            return True
        mine = self.recent[k]
        return mine.request_id == e.request_id and mine.payload == e.payload

    def _ensure_state(self, config: dict[str, Any]) -> MapState:
        if self.st is None:
            o = self.server.opts
            smap = StochasticMap.from_options(dict(config["options"]))
            st = MapState(self.name, smap, o.lru_size, o.id_ttl_s,
                          snapshot_every=int(config["snapshot_every"]),
                          snapshots_kept=int(config["snapshots_kept"]),
                          gate_defer=DeferOptions.from_dict(config.get("gate_defer")),
                          retract_window_bytes=config.get("retract_window_bytes"))
            self.checkpoint_every = max(1, int(config["checkpoint_every"]))
            self.disk_snapshot_every = max(0, int(config.get("disk_snapshot_every", 0)))
            rec = self.server.recorder
            if rec is not None:
                rec.config(st, self.checkpoint_every, server_id=self.server.server_id)
            self.st = st
        return self.st

    def _stop_following(self, why: str) -> None:
        self.stopped = why
        log.critical("map %r: standby stops following: %s", self.name, why)

    def _apply(self, e: Entry) -> None:
        st = self.st
        assert st is not None
        try:
            req = decode_input(e.op, e.payload, st.n_samples)
            ack = st.apply(e.op, req, time_ns=e.recv_ns, payload=e.payload)
        except McsmError as exc:
            self._stop_following(f"input seq {e.seq} ({e.op}) was refused here: "
                                 f"{type(exc).__name__}: {exc}")
            return
        self.recent.append(e)
        rec = self.server.recorder
        digest = st.digest() if e.digest is not None or ack.seq % self.checkpoint_every == 0 \
            else None
        try:
            if rec is not None:
                rec.input(e.op, self.name, ack.seq, e.recv_ns, e.sender, e.request_id,
                          e.payload)
                if ack.seq % self.checkpoint_every == 0 and digest is not None:
                    rec.checkpoint(self.name, ack.seq, digest, "periodic")
                if self.disk_snapshot_every and ack.seq % self.disk_snapshot_every == 0:
                    rec.snapshot(st)
        except (OSError, ValueError) as exc:
            log.critical("recording failed at seq %d of map %r: %s; stopping", ack.seq,
                         self.name, exc)
            self.server.failed.set()
            self._stop_following("recording failed")
            return
        if e.digest is not None and digest != e.digest:
            self._stop_following(f"digest differs from the primary's at seq {e.seq}")

    def _apply_batch(self, config: dict[str, Any], entries: list[Entry]) -> None:
        if self.stopped is not None or self.promoted:
            return
        self.sync = max(0, int(config.get("sync_standbys", 0)))
        self.epoch = max(0, int(config.get("epoch", 0)))
        st = self._ensure_state(config)
        for e in entries:
            if self.stopped is not None:
                return
            if e.seq <= st.seq:
                continue
            if e.seq != st.seq + 1:
                self._need.set()
                return
            self._apply(e)

    def _load(self, config: dict[str, Any], blob: bytes) -> None:
        if self.stopped is not None or self.promoted:
            return
        self.sync = max(0, int(config.get("sync_standbys", 0)))
        self.epoch = max(0, int(config.get("epoch", 0)))
        d = wire.unpack(blob, max_bytes=len(blob) + 1, max_map_len=1 << 20)
        seq = int(d["seq"])
        if self.st is not None and self.st.seq > 0:
            self._stop_following(f"fell behind the primary's log (at seq {self.st.seq}, the "
                                 f"primary sends a snapshot of seq {seq}): restart this "
                                 "standby with a new recording")
            return
        st = self._ensure_state(config)
        smap = StochasticMap.from_snapshot(decode_snapshot(d["state"], st.n_samples))
        st.import_ids(list(d.get("ids", [])))
        dfr = d.get("deferral")  # the held closure (--gate-defer), if any
        st.restore(seq, smap, dict(d.get("verdicts", {})),
                   None if dfr is None else DeferState.decode(dfr, st.n_samples))
        if st.digest() != str(d["digest"]):
            self._stop_following(f"the primary's snapshot of seq {seq} does not load to its "
                                 "digest")
            return
        if self.server.recorder is not None:
            self.server.recorder.snapshot(st)
        log.info("map %r: loaded the primary's snapshot of seq %d", self.name, seq)

    # ---------------------------------------------------------------- catch-up thread
    def _loop(self) -> None:
        while not self._stop.is_set():
            if not self._need.wait(0.5):
                continue
            self._need.clear()
            if self.promoted or self.stopped is not None or self.primary is None:
                continue
            try:
                self._catch_up()
            except (McsmError, zenoh.ZError, KeyError, TypeError, ValueError) as exc:
                log.warning("map %r: catch-up: %s; trying again", self.name, exc)
                self._stop.wait(0.5)
                self._need.set()

    def _ask(self, body: dict[str, Any]) -> dict[str, Any] | None:
        primary = self.primary
        if primary is None:
            return None
        replies = self.server.session.get(self.keys.log, payload=_pack(body), timeout=120.0,
                                          target=zenoh.QueryTarget.ALL,
                                          consolidation=zenoh.ConsolidationMode.NONE)
        for reply in replies:
            zid = str(reply.replier_id.zid) if reply.replier_id is not None else ""
            if zid != primary:
                continue
            if reply.ok is None:
                err = reply.err.payload.to_bytes() if reply.err is not None else b""
                raise wire.decode_error(err)
            return _unpack(reply.ok.payload.to_bytes())
        return None

    def _catch_up(self) -> None:
        for _ in range(100_000):  # bounded; each round applies at least one input or returns
            if self._stop.is_set() or self.promoted or self.stopped is not None:
                return
            d = self._ask({"from": self.seq})
            if d is None:
                self._need.set()
                self._stop.wait(0.2)
                return
            config = d["config"]
            if "snapshot" in d:
                blob = self._download(d["snapshot"])
                self.server.run_in_worker(functools.partial(self._load, config, blob),
                                          timeout_s=300.0)
            else:
                entries = [Entry.from_obj(x) for x in d["entries"]]
                self.server.run_in_worker(functools.partial(self._apply_batch, config, entries),
                                          timeout_s=300.0)
            if self.seq >= int(d["head"]):
                return

    def _download(self, part: dict[str, Any]) -> bytes:
        seq, size = int(part["seq"]), int(part["size"])
        chunks = [bytes(part["part"])]
        got = len(chunks[0])
        for _ in range(size // PART_BYTES + 2):
            if got >= size:
                break
            d = self._ask({"snapshot": [seq, got]})
            if d is None:
                raise McsmError("the primary went away during a snapshot download")
            chunk = bytes(d["snapshot"]["part"])
            if not chunk:
                break
            chunks.append(chunk)
            got += len(chunk)
        if got != size:
            raise McsmError(f"snapshot download: {got} of {size} bytes")
        return b"".join(chunks)

    # ---------------------------------------------------------------- takeover
    def _statuses(self) -> dict[str, int]:
        """Every live standby's seq (through each one's worker, after its queued inputs)."""
        out: dict[str, int] = {}
        replies = self.server.session.get(self.keys.standby_any, payload=_pack({"t": "status"}),
                                          timeout=2.0, target=zenoh.QueryTarget.ALL,
                                          consolidation=zenoh.ConsolidationMode.NONE)
        for reply in replies:
            if reply.ok is None:
                continue
            try:
                d = _unpack(reply.ok.payload.to_bytes())
                out[str(d["zid"])] = int(d["seq"])
            except (McsmError, KeyError, TypeError, ValueError):
                continue
        # this standby, after the inputs already queued on its worker
        out[self.server.server_id] = self.server.run_in_worker(
            lambda: self.seq if self.stopped is None and self.st is not None else -1,
            timeout_s=60.0)
        return out

    def connected(self) -> bool:
        """Whether this server still reaches any other Zenoh node (a router or a peer). A
        server cut off from the network sees every other server's token go away: it must not
        take that for the primary's death (a router restart would split the map in two)."""
        info = self.server.session.info
        return bool(list(info.routers_zid()) or list(info.peers_zid()))

    def _elect(self, lost: str) -> None:
        """Until a primary serves the map again: find the standby that takes over (the
        highest seq, then the smallest id) and promote this one if it is that standby. Runs
        on its own thread; ends when this server stops, takes over or follows a primary."""
        self._elections += 1
        isolated_logged = False
        self._stop.wait(SETTLE_S)  # let a lost link show in the session's routers and peers
        while not (self._stop.is_set() or self.promoted or self.primary is not None):
            if not self.connected():
                if not isolated_logged:
                    log.warning("map %r: primary %s lost, but this server reaches no router "
                                "or peer: not taking over while cut off", self.name, lost)
                    isolated_logged = True
                self._stop.wait(0.5)
                continue
            statuses = {z: s for z, s in self._statuses().items() if s >= 0}
            if self.primary is not None:
                return
            if not statuses:
                self._stop.wait(0.5)
                continue
            winner = min(statuses, key=lambda z: (-statuses[z], z))
            log.info("map %r: primary %s lost; standbys %s; %s takes over", self.name, lost,
                     statuses, winner)
            if winner == self.server.server_id:
                if self.server.run_in_worker(lambda: self.server.promote(self),
                                             timeout_s=60.0):
                    return
            if self._primary_seen.wait(3.0):
                return

    def became_primary(self) -> MapState:
        """Called by the server's worker once it declared the map's keys."""
        assert self.st is not None
        self.promoted = True
        self._stop.set()
        self._undeclare()
        return self.st


__all__ = ["TAKEOVER", "undeclare_all", "Entry", "Follower", "PrimaryLink", "ReplLog",
           "DEFAULT_LOG_ENTRIES", "DEFAULT_SYNC_TIMEOUT_S"]
