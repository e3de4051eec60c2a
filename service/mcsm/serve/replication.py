"""Replicated maps: each map's accepted inputs in a NATS JetStream stream, standbys that apply
it, and a lease that says which server may acknowledge.

``mcsm serve --nats URL`` joins a JetStream cluster (``mcsm nats-cluster``, three nodes; every
stream, bucket and object store has ``--replicas`` R = 3 copies, and JetStream answers a
publish once a quorum of them stored it). For each replicated map:

* **The log.** One stream (``MCSM_<prefix>_<map>``) holds the map's inputs, one message per
  applied input, in seq order: the map's seq is ``base`` + the stream seq (``base`` is the seq
  the map had when its stream was made, 0 unless it came from ``--restore``). A message is the
  input's recording record (operation, receive time, sender, request id, request bytes, and
  the digest at checkpoints), so a standby rebuilds the map exactly as replay does, and it
  carries any operation of the table (:data:`mcsm.log.topics.INPUT_TOPICS`) without knowing
  which. Its ``Nats-Msg-Id`` is the request id (de-duplication window: ``--id-ttl-s``).
* **Apply, append, then acknowledge.** The primary's worker applies an input (a refused
  input changes nothing and is never logged), publishes it with
  ``Nats-Expected-Last-Sequence`` = the stream seq it has applied, records it, and
  acknowledges it only when JetStream stored it on a quorum *and* the lease is still valid.
  Apply-then-publish keeps refused inputs out of the log (a replayer never meets one, and
  seqs stay dense); the price is a rollback when the append is refused, which is rare (another
  server appended: this one was deposed) and done by rebuilding the map from this server's
  own recording (every logged input is in it, nothing else), then following the stream.
* **An unknown outcome** (the publish timed out, the connection dropped) is resolved by
  publishing the same message again (same id, same expected sequence): JetStream checks the
  id before the expected sequence, so if the first attempt was stored the retry answers
  ``duplicate`` with its seq, and if it was not, the retry is stored or refused
  (``tests/service/test_nats_log.py`` checks this on a real cluster). A ``duplicate`` that
  this server did not cause (the id is in the log from another primary) is a refusal. If
  the log cannot be reached before the lease could have expired, the input is not
  acknowledged (``NotReplicated``, retryable) and the map is rebuilt as above.
* **The lease.** A key per map in the KV bucket ``MCSM_LEASE`` (a bucket TTL, ``--lease-ttl``,
  2 s by default): taken with compare-and-set (``create``), renewed with compare-and-set
  (``update`` on the revision this server wrote) every TTL/6. A server acknowledges only
  while ``now < t_sent + 0.75 TTL``, ``t_sent`` being when it sent its last successful renewal:
  JetStream stamps the entry after that, so no other server can hold the lease before then.
  A primary stopped by SIGINT/SIGTERM deletes its lease (a standby takes over at once); a
  SIGKILLed one's lease expires after the TTL.
* **Standbys** consume the stream (an ephemeral pull consumer from their seq + 1, fetched in
  bounded batches, applied through :meth:`MapState.apply` on the worker and recorded). A
  standby takes the lease when it is free, applies the whole stream (the head read after the
  lease was taken), and only then declares the map's Zenoh keys and acknowledges. The Zenoh
  liveliness token ``<prefix>/<map>/alive/<zid>`` stays, for clients to find the primary; it
  plays no part in the election.
* **Late standbys** start from the empty map and the whole stream when the stream reaches
  back to it; when retention (``--log-max-bytes``, ``--log-max-age``) dropped its beginning,
  from the latest snapshot in the object store ``MCSM_SNAP`` (written by the primary every
  ``--disk-snapshot-every`` inputs, with the remembered request ids) and the stream after it.

The modules: :mod:`mcsm.serve.replication_link` (the connection, the options, the buckets, NATS
names), :mod:`mcsm.serve.replication_log` (the entry codec; one map's stream, config, snapshot and
consumer), :mod:`mcsm.serve.replication_lease` (the lease); this module holds the replica: one map's
roles (standby, primary), its loop on the NATS thread and its work on the server's worker.

Nothing of this is imported by a server without ``--nats``.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from collections.abc import Awaitable, Callable
from typing import Any, TypeVar

from mcsm import wire
from mcsm.core.smap import StochasticMap
from mcsm.errors import McsmError
from mcsm.log.topics import decode_input
from mcsm.map.carry import decode_snapshot, encode_snapshot
from mcsm.map.deferral import DeferOptions, DeferState
from mcsm.map.state import MapState
from mcsm.serve.host import ReplicaHost
from mcsm.serve.replication_defaults import (
    DEFAULT_LEASE_TTL_S,
    DEFAULT_LOG_MAX_AGE_S,
    DEFAULT_LOG_MAX_BYTES,
    DEFAULT_REPLICAS,
)
from mcsm.serve.replication_lease import Lease
from mcsm.serve.replication_link import NatsLink, NatsOptions, retry, stream_name
from mcsm.serve.replication_log import Entry, MapLog, Refused, pack_entry, pack_obj

log = logging.getLogger(__name__)
T = TypeVar("T")

TAKEOVER = "takeover"
"""The event (``op`` and ``kind``) a standby publishes when it becomes the map's primary."""
STALL_S = 2.0
"""A standby behind the log whose consumer delivered nothing for this long makes a new one
(the old one may be gone: its node was cut off past its inactivity threshold, or restarted)."""


class Replica:
    """One replicated map on this server: its state, its role (``standby``, ``primary``),
    the lease and the stream consumer. The map's state changes on the server's worker only;
    the NATS loop fetches, renews and hands work to the worker."""

    def __init__(self, server: ReplicaHost, link: NatsLink, name: str, keys: wire.Keys,
                 claim: bool, state: MapState | None = None) -> None:
        self.server, self.link, self.name, self.keys = server, link, name, keys
        self.claim = claim  # --map: take the lease at start (refuse if another holds it)
        self.st = state
        self.log = MapLog(link, keys.prefix, name)
        self.lease = Lease(link.leases, self.log.key, server.server_id, link.lease_ttl_s)
        self.role = "standby"
        self.base = 0
        self.config: dict[str, Any] | None = None
        self.checkpoint_every = server.opts.checkpoint_every
        self.disk_snapshot_every = server.opts.disk_snapshot_every
        self.recorded = -1  # the last seq of this map in the recording (-1: none yet)
        self.dirty = False  # the state holds an input the log refused or may not hold
        self.stopped: str | None = None
        self.lost_at: float | None = None
        self.takeovers = 0
        self.standbys: dict[str, int] = {}
        self._stop = threading.Event()
        self._task: Any = None
        self._listing: asyncio.Task[None] | None = None  # the primary's standby listing
        self._keeper: asyncio.Task[None] | None = None  # the lease's renewals
        self._progress_at = time.monotonic()  # when the consumer last delivered (or was made)
        self._snap_busy = False
        self.promoted = threading.Event()

    # ------------------------------------------------------------ queries from the worker
    @property
    def seq(self) -> int:
        return self.st.seq if self.st is not None else -1

    @property
    def term(self) -> int:
        """The lease's revision when this server last took it (``info.epoch``)."""
        return self.lease.term

    def may_ack(self) -> bool:
        return self.role == "primary" and not self.dirty and self.lease.valid()

    # ------------------------------------------------------------ start (server thread)
    def start(self, timeout_s: float = 60.0) -> None:
        """Read (or make) the map's config and stream; with ``claim``, take the lease or
        raise; then run the replica's loop.

        Raises
        ------
        McsmError
            ``claim`` and another server holds the lease (the only check that refuses a
            replicated map already served), or the stream exists and this server restored
            another state.
        """
        self.link.run(self._setup(time.monotonic() + timeout_s - 1.0), timeout_s)
        self._task = self.link.spawn(self._main())
        self._task.add_done_callback(self._loop_ended)

    def _loop_ended(self, fut: Any) -> None:
        if self._stop.is_set():
            return
        exc = None if fut.cancelled() else fut.exception()
        self._stop_following(f"its replication loop ended: {exc!r}")

    async def _setup(self, deadline: float) -> None:
        """With ``claim``, the lease first: a standby sees a new map's config only once its
        primary holds the lease, so it never takes over a map whose primary is starting. The
        lease's renewals run from here on beside everything else (:meth:`_keep_lease`)."""
        if self._keeper is None:
            self._keeper = asyncio.create_task(self._keep_lease())
        if self.claim and not await retry("the map's lease", self.lease.acquire, deadline):
            holder = await self.lease.holder_now()
            raise McsmError(f"map {self.name!r} is served by server {holder} (it holds the "
                            "map's lease): refusing to serve it a second time (to follow it, "
                            f"start this server with --standby-of {self.name})")
        cfg = await self._step("the map's config", self.log.read_config, deadline)
        if cfg is None and self.claim:
            st = self.st
            assert st is not None
            if st.seq > 0:  # a restored map: its stream starts at its seq, from a snapshot
                blob = self._snapshot_blob(st)
                await self._step("the map's snapshot", lambda: self.log.upload(blob), deadline)
            mine = self._config_of(st)
            await self._step("the map's log", lambda: self.log.create(
                mine, self.server.opts.id_ttl_s), deadline)
            cfg = await self._step("the map's config", self.log.read_config, deadline)
        if cfg is not None:
            self._use_config(cfg)
        if not self.claim:
            return
        last = await self._step("the log's head", self.log.head, deadline)
        if self.st is not None and self.st.seq > 0 and self.st.seq != self.base + last:
            await self.lease.release()
            raise McsmError(f"map {self.name!r}: its log holds {last} inputs after seq "
                            f"{self.base}; this server restored seq {self.st.seq}: start it "
                            "without --restore (it catches up from the log)")
        if self.st is not None and self.st.seq == 0 and last > 0:
            self.st = None  # a new empty map, but the log has the map: build it from there

    async def _step(self, what: str, make: Callable[[], Awaitable[T]], deadline: float) -> T:
        """A step of starting (:func:`retry`; the lease is renewed beside it)."""
        return await retry(what, make, deadline)

    async def _keep_lease(self) -> None:
        """The lease's only renewer, from the start to :meth:`stop_loop`, beside everything
        else the replica does on the NATS loop: a step of starting, a consumer's creation or
        a fetch can each take longer than the lease's TTL when the cluster is slow or
        electing (a ``--map`` server lost its lease during a 5 s config read that way)."""
        poll = min(0.1, self.link.lease_ttl_s / 10)
        for _ in iter(int, 1):  # until cancelled (stop_loop)
            lease = self.lease
            try:
                if lease.holding and time.monotonic() >= lease.renew_at:
                    await lease.renew()  # False: lost (holding cleared); None: try again soon
            except asyncio.CancelledError:
                if self._stop.is_set():
                    raise
            except Exception as exc:  # renew() answers its own errors; anything else: go on
                log.warning("map %r: lease renewal: %s: %s", self.name, type(exc).__name__,
                            exc)
            wait = lease.renew_at - time.monotonic() if lease.holding else poll
            await asyncio.sleep(max(0.01, min(poll, wait)))

    def _config_of(self, st: MapState) -> dict[str, Any]:
        return {"options": st.map.options(), "n_samples": st.n_samples,
                "checkpoint_every": self.checkpoint_every, "base": st.seq,
                "disk_snapshot_every": self.disk_snapshot_every,
                "snapshot_every": st.history.snapshot_every,
                "snapshots_kept": st.history.snapshots_kept,
                "retract_window_bytes": st.history.max_bytes,
                "gate_defer": (None if st.deferral is None
                               else st.deferral.options.to_dict())}

    def _use_config(self, cfg: dict[str, Any]) -> None:
        self.config = cfg
        self.base = int(cfg.get("base", 0))
        self.checkpoint_every = max(1, int(cfg["checkpoint_every"]))
        self.disk_snapshot_every = max(0, int(cfg.get("disk_snapshot_every", 0)))

    # ------------------------------------------------------------ the loop (NATS thread)
    async def _main(self) -> None:
        poll = min(0.1, self.link.lease_ttl_s / 10)
        next_try = 0.0
        next_standbys = 0.0
        for _ in iter(int, 1):  # until stopped (cancelled, or self._stop)
            if self._stop.is_set():
                return
            try:
                if self.stopped is not None:
                    if self.lease.holding:
                        await self.lease.release()
                    await asyncio.sleep(0.5)
                elif self.role == "primary":
                    if not self.lease.holding:  # the keeper's renewal found it lost
                        await self._demote("lost the lease (it expired or another server "
                                           "holds it)")
                        continue
                    if time.monotonic() > next_standbys and (
                            self._listing is None or self._listing.done()):
                        # its own task: a slow listing must never hold back a renewal
                        self._listing = asyncio.create_task(self._refresh_standbys())
                        next_standbys = time.monotonic() + 1.0
                    await asyncio.sleep(poll)
                else:
                    if self.dirty and self.lease.holding:
                        await self.lease.release()
                    await self._standby_round()
                    if self.role == "standby" and self.st_ready() and (
                            self.lease.holding or time.monotonic() > next_try):
                        next_try = time.monotonic() + poll
                        if self.lease.holding or await self.lease.try_take():
                            await self._take_over()
            except asyncio.CancelledError:
                if self._stop.is_set():
                    raise
                # not ours (nats-py cancels a request when its connection drops): go on
                log.warning("map %r (%s): a NATS call was cancelled", self.name, self.role)
                await asyncio.sleep(0.2)
            except Exception as exc:  # NATS unreachable, a consumer gone: retry, bounded
                log.warning("map %r (%s): %s: %s", self.name, self.role, type(exc).__name__,
                            exc)
                await self.log.unfollow()
                await asyncio.sleep(0.2)

    def st_ready(self) -> bool:
        return self.st is not None and not self.dirty and self.stopped is None

    async def _take_over(self) -> None:
        """Holding the lease: apply the whole stream (its head as its leader sees it, read
        after the lease was taken), then serve."""
        loop = asyncio.get_running_loop()
        head = self.base + await self.log.head()
        for _ in range(1_000_000):
            if self.seq >= head or self.stopped is not None or self.dirty:
                break
            if not self.lease.holding:  # lost while catching up (the keeper renews it)
                return
            await self._standby_round()
        if self.seq != head or self.stopped is not None or self.dirty:
            await self.lease.release()
            return
        await self.log.unfollow()
        ok = await loop.run_in_executor(None, lambda: self.server.run_in_worker(
            lambda: self.server.promote(self), timeout_s=60.0))
        if not ok:
            await self.lease.release()

    async def _demote(self, why: str) -> None:
        loop = asyncio.get_running_loop()
        self.lease.valid_until = 0.0
        log.warning("map %r: stops being primary: %s", self.name, why)
        await loop.run_in_executor(None, lambda: self.server.run_in_worker(
            lambda: self.server.demote(self, why), timeout_s=120.0))

    async def _refresh_standbys(self) -> None:
        try:
            got = await self.log.standbys()
        except Exception as exc:  # the list stays as it was; tried again in a second
            log.info("map %r: listing the standbys: %s: %s", self.name, type(exc).__name__,
                     exc)
            return
        self.standbys = {sid: self.base + seq for sid, seq in got.items()}

    # ------------------------------------------------------------ standby: fetch and apply
    async def _standby_round(self) -> None:
        loop = asyncio.get_running_loop()
        if self.dirty:
            await loop.run_in_executor(None, lambda: self.server.run_in_worker(
                self._rebuild, timeout_s=600.0))
            return
        if self.st is None:
            await self._load_start()
            return
        if not self.log.following:
            await self.log.follow(self.seq - self.base + 1)
            self._progress_at = time.monotonic()
        entries = [(self.base + s, e) for s, e in await self.log.fetch()]
        if entries:
            self._progress_at = time.monotonic()
            await loop.run_in_executor(None, lambda: self.server.run_in_worker(
                lambda: self._apply_batch(entries), timeout_s=600.0))
        elif time.monotonic() - self._progress_at > STALL_S:
            await self._check_stall()

    async def _check_stall(self) -> None:
        """Nothing delivered for :data:`STALL_S`: if the log is ahead of this standby, its
        consumer is stuck (gone with a cut-off node, or left behind on a lagging one): make
        a new one from this standby's seq."""
        self._progress_at = time.monotonic()
        _, last = await self.log.bounds()
        if self.base + last <= self.seq:
            return
        log.warning("map %r: the log is at seq %d, this standby at %d, and its consumer "
                    "delivered nothing for %.0f s (%s): a new consumer", self.name,
                    self.base + last, self.seq, STALL_S, await self.log.describe_consumer())
        await self.log.unfollow()

    async def _load_start(self) -> None:
        """A new standby: the empty map if the stream reaches back to it, else the latest
        snapshot in the object store (when the stream continues it)."""
        loop = asyncio.get_running_loop()
        cfg = await self.log.read_config()
        if cfg is None:
            await asyncio.sleep(0.5)  # the map's primary has not made its log yet
            return
        self._use_config(cfg)
        first, _ = await self.log.bounds()  # the oldest stream seq still held
        if self.base == 0 and first <= 1:
            await loop.run_in_executor(None, lambda: self.server.run_in_worker(
                lambda: self._new_state(None), timeout_s=300.0))
            return
        blob = await self.log.download()
        if blob is None:
            log.warning("map %r: the log starts at seq %d and no snapshot covers it; waiting",
                        self.name, self.base + first)
            await asyncio.sleep(1.0)
            return
        d = wire.unpack(blob, max_bytes=len(blob) + 1, max_map_len=1 << 20)
        if int(d["seq"]) < self.base + first - 1:
            log.warning("map %r: the latest snapshot (seq %d) is older than the log's start "
                        "(seq %d); waiting for a newer one", self.name, d["seq"],
                        self.base + first)
            await asyncio.sleep(1.0)
            return
        await loop.run_in_executor(None, lambda: self.server.run_in_worker(
            lambda: self._new_state(d), timeout_s=300.0))

    # ------------------------------------------------------------ snapshots
    def _snapshot_blob(self, st: MapState) -> bytes:
        return pack_obj({"seq": st.seq, "digest": st.digest(), "verdicts": dict(st.verdicts),
                         "state": encode_snapshot(st.map.snapshot()), "ids": st.export_ids(),
                         "deferral": None if st.deferral is None
                         else st.deferral.state.encode()})

    def snapshot_soon(self) -> None:
        """On the worker, after an input at a ``--disk-snapshot-every`` seq: upload a
        snapshot for late standbys (one at a time; skipped while one is uploading)."""
        if self._snap_busy or self.st is None:
            return
        self._snap_busy = True
        blob = self._snapshot_blob(self.st)

        async def up() -> None:
            try:
                await self.log.upload(blob)
            except Exception as exc:
                log.warning("map %r: snapshot upload: %s", self.name, exc)
            finally:
                self._snap_busy = False

        self.link.spawn(up())

    # ------------------------------------------------------------ the worker's side
    def _new_state(self, snap: dict[str, Any] | None) -> None:
        cfg = self.config
        assert cfg is not None
        o = self.server.opts
        st = MapState(self.name, StochasticMap.from_options(dict(cfg["options"])), o.lru_size,
                      o.id_ttl_s, snapshot_every=int(cfg["snapshot_every"]),
                      snapshots_kept=int(cfg["snapshots_kept"]),
                      gate_defer=DeferOptions.from_dict(cfg.get("gate_defer")),
                      retract_window_bytes=cfg.get("retract_window_bytes"))
        rec = self.server.recorder
        if rec is not None and self.recorded < 0:
            rec.config(st, self.checkpoint_every, server_id=self.server.server_id)
            self.recorded = 0
        if snap is not None:
            smap = StochasticMap.from_snapshot(decode_snapshot(snap["state"], st.n_samples))
            st.import_ids(list(snap.get("ids", [])))
            dfr = snap.get("deferral")
            st.restore(int(snap["seq"]), smap, dict(snap.get("verdicts", {})),
                       None if dfr is None else DeferState.decode(dfr, st.n_samples))
            if st.digest() != str(snap["digest"]):
                self._stop_following(f"the snapshot of seq {snap['seq']} does not load to "
                                     "its digest")
                return
            if rec is not None:
                rec.snapshot(st)
                self.recorded = st.seq
            log.info("map %r: loaded the snapshot of seq %d", self.name, st.seq)
        self.st = st

    def _stop_following(self, why: str) -> None:
        self.stopped = why
        log.critical("map %r: this server stops following it: %s", self.name, why)

    def _apply_batch(self, entries: list[tuple[int, Entry]]) -> None:
        if self.role != "standby" or self.stopped is not None or self.dirty:
            return
        st = self.st
        assert st is not None
        for seq, e in entries:
            if seq <= st.seq:
                continue
            if seq != st.seq + 1 or e.seq != seq:
                self._stop_following(f"the log's seq {seq} follows seq {st.seq} here: the "
                                     "log no longer reaches back to this standby (retention)"
                                     "; restart it with a new recording")
                return
            if not self.apply_entry(e):
                return

    def apply_entry(self, e: Entry) -> bool:
        """Apply and record one logged input (as replay does); False if this standby stopped."""
        st = self.st
        assert st is not None
        try:
            req = decode_input(e.op, e.payload, st.n_samples)
            ack = st.apply(e.op, req, time_ns=e.recv_ns, payload=e.payload)
        except McsmError as exc:
            self._stop_following(f"input seq {e.seq} ({e.op}) was refused here: "
                                 f"{type(exc).__name__}: {exc}")
            return False
        digest = st.digest() if e.digest is not None or ack.seq % self.checkpoint_every == 0 \
            else None
        rec = self.server.recorder
        try:
            if rec is not None and ack.seq > self.recorded:
                rec.input(e.op, self.name, ack.seq, e.recv_ns, e.sender, e.request_id,
                          e.payload)
                self.recorded = ack.seq
                if ack.seq % self.checkpoint_every == 0 and digest is not None:
                    rec.checkpoint(self.name, ack.seq, digest, "periodic")
                if self.disk_snapshot_every and ack.seq % self.disk_snapshot_every == 0:
                    rec.snapshot(st)
        except (OSError, ValueError) as exc:
            log.critical("recording failed at seq %d of map %r: %s; stopping", ack.seq,
                         self.name, exc)
            self.server.failed.set()
            self._stop_following("recording failed")
            return False
        if e.digest is not None and digest != e.digest:
            self._stop_following(f"digest differs from the log's at seq {e.seq}")
            return False
        return True

    def append(self, e: Entry) -> int:
        """On the worker, for an input just applied (map seq ``e.seq``): put it in the log,
        trying while the lease is valid; returns its map seq.

        Raises
        ------
        Refused
            The log refused it or could not be reached before the lease could expire: the
            state now holds an input the log may not (``dirty``).
        """
        expected = e.seq - 1 - self.base
        deadline = max(self.lease.valid_until, time.monotonic()) + 0.05
        try:
            return self.base + self.link.run(
                self.log.publish(e.pack(), e.request_id, expected, deadline),
                timeout_s=deadline - time.monotonic() + 2 * self.link.lease_ttl_s)
        except Refused:
            self.dirty = True
            raise
        except Exception as exc:
            self.dirty = True
            raise Refused(f"{type(exc).__name__}: {exc}") from None

    def _rebuild(self) -> None:
        """On the worker: the state holds an input the log refused: rebuild it from this
        server's recording (every logged input it applied, nothing else), then follow."""
        from mcsm.log.replay import replay

        rec = self.server.recorder
        self.st = None
        self._drop_from_server()
        if rec is None:  # no recording: start over from the log
            self.recorded = -1
            self.dirty = False
            return
        # every file of a split recording (replay starts from the one with the latest snapshot)
        rep = replay(list(rec.paths), from_snapshot=True, lru_size=self.server.opts.lru_size)
        st = rep.states.get(self.name)
        if rep.divergence is not None or st is None or st.seq != self.recorded:
            self._stop_following(f"its own recording does not rebuild it (at seq "
                                 f"{None if st is None else st.seq}, recorded "
                                 f"{self.recorded}: {rep.divergence})")
            self.dirty = False
            return
        st.id_ttl_s = self.server.opts.id_ttl_s
        self.st = st
        self.dirty = False
        log.warning("map %r: rebuilt from the recording at seq %d (%d inputs); following "
                    "the log", self.name, st.seq, rep.n_inputs)

    def _drop_from_server(self) -> None:
        self.server.states.pop(self.name, None)

    # ------------------------------------------------------------ stop
    def stop_loop(self) -> None:
        """Stop fetching, renewing and taking over (the worker may still append)."""
        self._stop.set()
        if self._task is not None:
            self._task.cancel()
        keeper = self._keeper
        if keeper is not None and self.link.loop.is_running():
            self.link.loop.call_soon_threadsafe(keeper.cancel)

    def close(self, release: bool) -> None:
        self.stop_loop()
        try:
            self.link.run(self._close(release), 5.0)
        except Exception as exc:
            log.debug("replica close: %s", exc)

    async def _close(self, release: bool) -> None:
        await self.log.unfollow()
        if release and self.role == "primary":
            await self.lease.release()


__all__ = ["DEFAULT_LEASE_TTL_S", "DEFAULT_LOG_MAX_AGE_S", "DEFAULT_LOG_MAX_BYTES",
           "DEFAULT_REPLICAS", "TAKEOVER", "Entry", "NatsLink", "NatsOptions", "Refused",
           "Replica", "pack_entry", "stream_name"]
