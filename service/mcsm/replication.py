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
  carries any operation of the table (:data:`mcsm.recording.INPUT_TOPICS`) without knowing
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

Nothing of this is imported by a server without ``--nats``.
"""

from __future__ import annotations

import asyncio
import json
import logging
import re
import threading
import time
from collections.abc import Coroutine
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

from mcsm import wire
from mcsm.core.smap import StochasticMap
from mcsm.deferral import DeferOptions, DeferState
from mcsm.errors import BadMessage, McsmError
from mcsm.recording import INPUT_TOPICS, decode_input, decode_snapshot, encode_snapshot
from mcsm.replication_defaults import (
    DEFAULT_LEASE_TTL_S,
    DEFAULT_LOG_MAX_AGE_S,
    DEFAULT_LOG_MAX_BYTES,
    DEFAULT_REPLICAS,
)
from mcsm.state import MapState

if TYPE_CHECKING:
    from mcsm.server import Server

log = logging.getLogger(__name__)
T = TypeVar("T")

LEASE_BUCKET = "MCSM_LEASE"
MAPS_BUCKET = "MCSM_MAPS"
SNAP_BUCKET = "MCSM_SNAP"
VALID_FRACTION = 0.75
"""A primary acknowledges until ``t_sent + VALID_FRACTION * TTL`` (the lease lasts until
``t_stored + TTL`` at least, ``t_stored >= t_sent``)."""
FETCH_BATCH = 32
"""Inputs a standby fetches at once (its memory bound: this many inputs of at most 8 MiB)."""
TAKEOVER = "takeover"
"""The event (``op`` and ``kind``) a standby publishes when it becomes the map's primary."""
_MAX_MSG = 64 * 1024 * 1024


@dataclass
class NatsOptions:
    """``mcsm serve --nats ...``: where the log is and how it is kept."""

    urls: list[str]
    user: str | None = None
    password: str | None = None
    tls_ca: str | None = None
    tls_cert: str | None = None
    tls_key: str | None = None
    replicas: int = DEFAULT_REPLICAS
    lease_ttl_s: float = DEFAULT_LEASE_TTL_S
    max_bytes: int = DEFAULT_LOG_MAX_BYTES
    max_age_s: float = DEFAULT_LOG_MAX_AGE_S
    append_timeout_s: float = 1.0
    extra: dict[str, Any] = field(default_factory=dict)

    @staticmethod
    def load_auth(path: str | Path) -> dict[str, str]:
        """A server identity's NATS credentials file (``deploy/``): a JSON object with
        ``user`` and ``password`` (and optionally ``tls_ca``, ``tls_cert``, ``tls_key``).

        Raises
        ------
        McsmError
            If it cannot be read or is not such an object.
        """
        try:
            d = json.loads(Path(path).read_text())
        except (OSError, ValueError) as exc:
            raise McsmError(f"--nats-auth {path}: {exc}") from None
        keys = ("user", "password", "tls_ca", "tls_cert", "tls_key")
        if not isinstance(d, dict) or any(k not in keys or not isinstance(v, str)
                                          for k, v in d.items()):
            raise McsmError(f"--nats-auth {path}: expected a JSON object of strings with keys "
                            f"among {keys}")
        return {str(k): str(v) for k, v in d.items()}


def _pack(obj: dict[str, Any]) -> bytes:
    return wire.pack({"v": wire.VERSION, **obj})


def _enc(text: str) -> str:
    """A name for NATS (streams, subjects, keys): ``[A-Za-z0-9-]`` kept, the rest ``_xx``."""
    return re.sub(r"[^A-Za-z0-9-]", lambda m: f"_{ord(m.group()):02x}", text)


def stream_name(prefix: str, map_name: str) -> str:
    return f"MCSM_{_enc(prefix)}_{_enc(map_name)}"


def pack_entry(seq: int, op: str, recv_ns: int, sender: str, request_id: str, payload: bytes,
               digest: str | None) -> bytes:
    return wire.pack({"v": wire.VERSION, "seq": seq, "op": op, "recv_ns": recv_ns,
                      "sender": sender, "id": request_id, "request": payload,
                      "digest": digest})


@dataclass(frozen=True)
class Entry:
    """One logged input (a stream message)."""

    seq: int
    op: str
    recv_ns: int
    sender: str
    request_id: str
    payload: bytes
    digest: str | None

    @staticmethod
    def unpack(data: bytes) -> Entry:
        """Checked inverse of :func:`pack_entry`.

        Raises
        ------
        BadMessage
            If a field is missing or of the wrong type.
        """
        d = wire.unpack(data, max_bytes=_MAX_MSG, max_map_len=64)
        seq, op, recv, sender, rid, req, dig = (d.get(k) for k in (
            "seq", "op", "recv_ns", "sender", "id", "request", "digest"))
        if type(seq) is not int or seq < 1 or type(recv) is not int:
            raise BadMessage("entry.seq/recv_ns", "integers", f"{seq!r}, {recv!r}")
        if op not in INPUT_TOPICS:
            raise BadMessage("entry.op", f"one of {sorted(INPUT_TOPICS)}", repr(op)[:40])
        if not isinstance(sender, str) or not isinstance(rid, str) \
                or not isinstance(req, bytes) or not (dig is None or isinstance(dig, str)):
            raise BadMessage("entry", "sender, id: str; request: bytes; digest: str or nil",
                             "other types")
        return Entry(seq, str(op), recv, sender, rid, req, dig)


class Refused(Exception):
    """The log did not take an input (another server appended, or it could not be reached
    in time); the map must be rebuilt before this server serves it again."""


# ------------------------------------------------------------------------------ connection
class NatsLink:
    """One server's connection to the cluster: an asyncio loop on its own thread, the
    lease, config and snapshot buckets. Other threads call :meth:`run`."""

    def __init__(self, opts: NatsOptions, server_id: str) -> None:
        self.opts = opts
        self.server_id = server_id
        self.loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self.loop.run_forever, name="mcsm-nats",
                                        daemon=True)
        self.nc: Any = None
        self.js: Any = None
        self.leases: Any = None
        self.maps: Any = None
        self.snaps: Any = None
        self.lease_ttl_s = float(opts.lease_ttl_s)

    def start(self, timeout_s: float = 30.0) -> None:
        """Connect and make (or open) the buckets.

        Raises
        ------
        McsmError
            If the cluster cannot be reached or refuses.
        """
        self._thread.start()
        try:
            self.run(self._connect(), timeout_s)
        except Exception as exc:
            self.close()
            raise McsmError(f"cannot use the NATS cluster {','.join(self.opts.urls)}: "
                            f"{type(exc).__name__}: {exc}") from None

    def run(self, coro: Coroutine[Any, Any, T], timeout_s: float) -> T:
        """Run ``coro`` on the loop and wait (at most ``timeout_s``) for its result."""
        fut = asyncio.run_coroutine_threadsafe(coro, self.loop)
        try:
            return fut.result(timeout_s)
        except TimeoutError:
            fut.cancel()
            raise

    def spawn(self, coro: Coroutine[Any, Any, Any]) -> Any:
        return asyncio.run_coroutine_threadsafe(coro, self.loop)

    async def _connect(self) -> None:
        import ssl

        import nats
        from nats.js.api import KeyValueConfig, ObjectStoreConfig

        o = self.opts
        kw: dict[str, Any] = {}
        if o.user is not None:
            kw.update(user=o.user, password=o.password or "")
        if o.tls_ca is not None:
            ctx = ssl.create_default_context(cafile=o.tls_ca)
            if o.tls_cert is not None:
                ctx.load_cert_chain(o.tls_cert, o.tls_key)
            kw["tls"] = ctx

        async def on_error(exc: Exception) -> None:
            log.info("nats: %s", exc)

        async def on_disc() -> None:
            log.warning("nats: disconnected")

        async def on_reconn() -> None:
            log.warning("nats: reconnected")

        self.nc = await nats.connect(
            servers=list(o.urls), name=f"mcsm {self.server_id}", connect_timeout=2,
            allow_reconnect=True, max_reconnect_attempts=-1, reconnect_time_wait=0.2,
            ping_interval=1, max_outstanding_pings=3, error_cb=on_error,
            disconnected_cb=on_disc, reconnected_cb=on_reconn, **kw)
        self.js = self.nc.jetstream(timeout=5.0)
        r = max(1, int(o.replicas))
        self.leases = await self._bucket(KeyValueConfig(
            bucket=LEASE_BUCKET, history=1, ttl=float(o.lease_ttl_s), replicas=r))
        self.maps = await self._bucket(KeyValueConfig(bucket=MAPS_BUCKET, history=1,
                                                      replicas=r))
        try:
            self.snaps = await self.js.create_object_store(
                SNAP_BUCKET, config=ObjectStoreConfig(replicas=r))
        except Exception:  # made by another server with other settings: use it as it is
            self.snaps = await self.js.object_store(SNAP_BUCKET)
        info = await self.js.stream_info(f"KV_{LEASE_BUCKET}")
        ttl = float(info.config.max_age or 0.0)
        if ttl > 0 and abs(ttl - self.lease_ttl_s) > 1e-6:
            log.warning("the fleet's lease TTL is %.3g s (bucket %s), not --lease-ttl %.3g s",
                        ttl, LEASE_BUCKET, self.lease_ttl_s)
            self.lease_ttl_s = ttl

    async def _bucket(self, cfg: Any) -> Any:
        try:
            return await self.js.create_key_value(cfg)
        except Exception:  # exists with other settings (another server made it)
            return await self.js.key_value(cfg.bucket)

    def close(self) -> None:
        if self.nc is not None:
            try:
                self.run(self.nc.close(), 5.0)
            except Exception as exc:  # already gone
                log.debug("nats close: %s", exc)
        if self.loop.is_running():
            self.loop.call_soon_threadsafe(self.loop.stop)
            self._thread.join(timeout=5.0)


# ------------------------------------------------------------------------------ one map
class Replica:
    """One replicated map on this server: its state, its role (``standby``, ``primary``),
    the lease and the stream consumer. The map's state changes on the server's worker only;
    the NATS loop fetches, renews and hands work to the worker."""

    def __init__(self, server: Server, link: NatsLink, name: str, keys: wire.Keys,
                 claim: bool, state: MapState | None = None) -> None:
        self.server, self.link, self.name, self.keys = server, link, name, keys
        self.claim = claim  # --map: take the lease at start (refuse if another holds it)
        self.st = state
        self.stream = stream_name(keys.prefix, name)
        self.subject = f"mcsm.{_enc(keys.prefix)}.{_enc(name)}"
        self.lease_key = f"{_enc(keys.prefix)}.{_enc(name)}"
        self.role = "standby"
        self.base = 0
        self.config: dict[str, Any] | None = None
        self.checkpoint_every = server.opts.checkpoint_every
        self.disk_snapshot_every = server.opts.disk_snapshot_every
        self.recorded = -1  # the last seq of this map in the recording (-1: none yet)
        self.dirty = False  # the state holds an input the log refused or may not hold
        self.stopped: str | None = None
        self.lease_rev = 0
        self.term = 0  # the lease's revision when this server took it (info.epoch)
        self.holding = False  # this server took the lease and has not lost it
        self.renew_at = 0.0
        self.valid_until = 0.0
        self.lost_at: float | None = None
        self.takeovers = 0
        self.standbys: dict[str, int] = {}
        self._sub: Any = None
        self._consumers = 0
        self._stop = threading.Event()
        self._task: Any = None
        self._snap_busy = False
        self.promoted = threading.Event()

    # ------------------------------------------------------------ queries from the worker
    @property
    def seq(self) -> int:
        return self.st.seq if self.st is not None else -1

    def may_ack(self) -> bool:
        return self.role == "primary" and not self.dirty and \
            time.monotonic() < self.valid_until

    # ------------------------------------------------------------ start (server thread)
    def start(self, timeout_s: float = 60.0) -> None:
        """Read (or make) the map's config and stream; with ``claim``, take the lease or
        raise; then run the replica's loop.

        Raises
        ------
        McsmError
            ``claim`` and another server holds the lease, or the stream exists and this
            server restored another state.
        """
        self.link.run(self._setup(), timeout_s)
        self._task = self.link.spawn(self._main())

    async def _setup(self) -> None:
        from nats.js.api import DiscardPolicy, StorageType, StreamConfig
        from nats.js.errors import KeyNotFoundError, KeyWrongLastSequenceError

        o, so = self.link.opts, self.server.opts
        cfg = await self._read_config()
        if cfg is None and self.claim:
            st = self.st
            assert st is not None
            mine = self._config_of(st)
            if st.seq > 0:  # a restored map: its stream starts at its seq, from a snapshot
                await self._upload(self._snapshot_blob(st))
            await self.link.js.add_stream(StreamConfig(
                name=self.stream, subjects=[self.subject], num_replicas=max(1, o.replicas),
                storage=StorageType.FILE, discard=DiscardPolicy.OLD,
                max_bytes=int(o.max_bytes) if o.max_bytes > 0 else None,
                max_age=float(o.max_age_s) if o.max_age_s > 0 else None,
                duplicate_window=max(1.0, float(so.id_ttl_s)), allow_direct=True,
                max_msg_size=min(16 << 20, int(o.max_bytes)) if o.max_bytes > 0 else 16 << 20))
            try:
                await self.link.maps.create(self.lease_key, _pack(mine))
            except KeyWrongLastSequenceError:
                pass  # another server made it meanwhile: use its
            cfg = await self._read_config()
        if cfg is not None:
            self._use_config(cfg)
        if not self.claim:
            return
        try:
            ok = await self._acquire()
        except KeyNotFoundError:
            ok = False
        if not ok:
            holder = await self._holder()
            raise McsmError(f"map {self.name!r} is served by server {holder} (it holds the "
                            "map's lease): refusing to serve it a second time (to follow it, "
                            f"start this server with --standby-of {self.name})")
        si = await self.link.js.stream_info(self.stream)
        if self.st is not None and self.st.seq > 0 and \
                self.st.seq != self.base + int(si.state.last_seq):
            await self._release()
            raise McsmError(f"map {self.name!r}: its log holds {si.state.last_seq} inputs "
                            f"after seq {self.base}; this server restored seq {self.st.seq}: "
                            "start it without --restore (it catches up from the log)")
        if self.st is not None and self.st.seq == 0 and si.state.last_seq > 0:
            self.st = None  # a new empty map, but the log has the map: build it from there

    def _config_of(self, st: MapState) -> dict[str, Any]:
        return {"options": st.map.options(), "n_samples": st.n_samples,
                "checkpoint_every": self.checkpoint_every, "base": st.seq,
                "disk_snapshot_every": self.disk_snapshot_every,
                "snapshot_every": st.history.snapshot_every,
                "snapshots_kept": st.history.snapshots_kept,
                "gate_defer": (None if st.deferral is None
                               else st.deferral.options.to_dict())}

    def _use_config(self, cfg: dict[str, Any]) -> None:
        self.config = cfg
        self.base = int(cfg.get("base", 0))
        self.checkpoint_every = max(1, int(cfg["checkpoint_every"]))
        self.disk_snapshot_every = max(0, int(cfg.get("disk_snapshot_every", 0)))

    async def _read_config(self) -> dict[str, Any] | None:
        from nats.js.errors import KeyNotFoundError

        try:
            e = await self.link.maps.get(self.lease_key)
        except KeyNotFoundError:
            return None
        d = wire.unpack(bytes(e.value), max_bytes=1 << 20, max_map_len=64)
        return dict(d)

    # ------------------------------------------------------------ the lease
    async def _acquire(self) -> bool:
        from nats.js.errors import KeyNotFoundError, KeyWrongLastSequenceError

        t0 = time.monotonic()
        try:
            rev = await asyncio.wait_for(self.link.leases.create(
                self.lease_key, self.server.server_id.encode()), self.link.lease_ttl_s / 2)
        except (KeyWrongLastSequenceError, KeyNotFoundError):
            return False  # held (or expiring while nats-py looked: try again)
        self.lease_rev = self.term = int(rev)
        self.holding = True
        self.valid_until = t0 + VALID_FRACTION * self.link.lease_ttl_s
        self.renew_at = t0 + self.link.lease_ttl_s / 6
        return True

    async def _renew(self) -> bool | None:
        """True: renewed; False: lost (another holds it, or it expired); None: unknown."""
        from nats.js.errors import KeyWrongLastSequenceError

        t0 = time.monotonic()
        try:
            rev = await asyncio.wait_for(self.link.leases.update(
                self.lease_key, self.server.server_id.encode(), last=self.lease_rev),
                self.link.lease_ttl_s / 4)
        except KeyWrongLastSequenceError:
            self.holding = False
            self.valid_until = 0.0
            return False
        except Exception as exc:  # timeout, no quorum, disconnected: try again
            log.info("map %r: lease renewal: %s", self.name, type(exc).__name__)
            return None
        self.lease_rev = int(rev)
        self.valid_until = t0 + VALID_FRACTION * self.link.lease_ttl_s
        self.renew_at = t0 + self.link.lease_ttl_s / 6
        return True

    async def _release(self) -> None:
        try:
            await asyncio.wait_for(self.link.leases.delete(self.lease_key,
                                                           last=self.lease_rev), 2.0)
        except Exception as exc:  # expired already, or unreachable: it expires by itself
            log.info("map %r: lease not released: %s", self.name, exc)
        self.valid_until = 0.0
        self.holding = False

    async def _holder(self) -> str:
        try:
            return bytes((await self.link.leases.get(self.lease_key)).value).decode()
        except Exception:
            return "?"

    # ------------------------------------------------------------ the loop (NATS thread)
    async def _main(self) -> None:
        poll = min(0.1, self.link.lease_ttl_s / 10)
        next_try = 0.0
        next_standbys = 0.0
        while not self._stop.is_set():
            try:
                if self.stopped is not None:
                    if self.holding:
                        await self._release()
                    await asyncio.sleep(0.5)
                elif self.role == "primary":
                    got = await self._renew() if time.monotonic() >= self.renew_at else True
                    if got is False:
                        await self._demote("lost the lease (it expired or another server "
                                           "holds it)")
                        continue
                    if time.monotonic() > next_standbys:
                        await self._refresh_standbys()
                        next_standbys = time.monotonic() + 1.0
                    await asyncio.sleep(max(0.0, min(poll, self.renew_at - time.monotonic())))
                else:
                    if self.dirty and self.holding:
                        await self._release()
                    elif self.holding and time.monotonic() >= self.renew_at:
                        await self._renew()
                    await self._standby_round()
                    if self.role == "standby" and self.st_ready() and (
                            self.holding or time.monotonic() > next_try):
                        next_try = time.monotonic() + poll
                        if self.holding or await self._try_lease():
                            await self._take_over()
            except asyncio.CancelledError:
                raise
            except Exception as exc:  # NATS unreachable, a consumer gone: retry, bounded
                log.warning("map %r (%s): %s: %s", self.name, self.role, type(exc).__name__,
                            exc)
                await self._drop_consumer()
                await asyncio.sleep(0.2)

    def st_ready(self) -> bool:
        return self.st is not None and not self.dirty and self.stopped is None

    async def _try_lease(self) -> bool:
        from nats.js.errors import KeyNotFoundError

        try:
            await asyncio.wait_for(self.link.leases.get(self.lease_key), 1.0)
            return False  # held
        except KeyNotFoundError:
            pass  # free (never taken, expired or deleted)
        return await self._acquire()

    async def _take_over(self) -> None:
        """Holding the lease: apply the whole stream, then serve."""
        loop = asyncio.get_running_loop()
        si = await self.link.js.stream_info(self.stream)
        head = self.base + int(si.state.last_seq)
        for _ in range(1_000_000):
            if self.seq >= head or self.stopped is not None or self.dirty:
                break
            if time.monotonic() >= self.renew_at:
                if await self._renew() is False:
                    return
            await self._standby_round()
        if self.seq != head or self.stopped is not None or self.dirty:
            await self._release()
            return
        await self._drop_consumer()
        ok = await loop.run_in_executor(None, lambda: self.server.run_in_worker(
            lambda: self.server.promote(self), timeout_s=60.0))
        if not ok:
            await self._release()

    async def _demote(self, why: str) -> None:
        loop = asyncio.get_running_loop()
        self.valid_until = 0.0
        log.warning("map %r: stops being primary: %s", self.name, why)
        await loop.run_in_executor(None, lambda: self.server.run_in_worker(
            lambda: self.server.demote(self, why), timeout_s=120.0))

    async def _refresh_standbys(self) -> None:
        out: dict[str, int] = {}
        try:
            for ci in await asyncio.wait_for(self.link.js.consumers_info(self.stream), 1.0):
                desc = ci.config.description or ""
                if desc.startswith("standby ") and ci.delivered is not None:
                    out[desc[8:]] = self.base + int(ci.delivered.stream_seq or 0)
        except Exception as exc:
            log.debug("consumers: %s", exc)
            return
        self.standbys = out

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
        if self._sub is None:
            await self._make_consumer()
        try:
            msgs = await self._sub.fetch(FETCH_BATCH, timeout=0.25)
        except TimeoutError:
            return
        entries: list[tuple[int, Entry]] = []
        for m in msgs:
            entries.append((self.base + int(m.metadata.sequence.stream), Entry.unpack(m.data)))
        if entries:
            await loop.run_in_executor(None, lambda: self.server.run_in_worker(
                lambda: self._apply_batch(entries), timeout_s=600.0))

    async def _make_consumer(self) -> None:
        from nats.js.api import AckPolicy, ConsumerConfig, DeliverPolicy

        await self._drop_consumer()
        self._consumers += 1
        name = f"sb-{self.server.server_id}-{self._consumers}"
        start = self.seq - self.base + 1
        await self.link.js.add_consumer(self.stream, ConsumerConfig(
            name=name, description=f"standby {self.server.server_id}",
            deliver_policy=DeliverPolicy.BY_START_SEQUENCE, opt_start_seq=max(1, start),
            ack_policy=AckPolicy.NONE, inactive_threshold=10.0, mem_storage=True,
            num_replicas=1))
        self._sub = await self.link.js.pull_subscribe_bind(
            consumer=name, stream=self.stream, pending_msgs_limit=4 * FETCH_BATCH,
            pending_bytes_limit=4 * FETCH_BATCH * 9 * 1024 * 1024)

    async def _drop_consumer(self) -> None:
        sub, self._sub = self._sub, None
        if sub is None:
            return
        try:
            await sub.unsubscribe()
            await asyncio.wait_for(self.link.js.delete_consumer(
                self.stream, f"sb-{self.server.server_id}-{self._consumers}"), 1.0)
        except Exception as exc:  # gone already; it expires when inactive
            log.debug("consumer: %s", exc)

    async def _load_start(self) -> None:
        """A new standby: the empty map if the stream reaches back to it, else the latest
        snapshot in the object store (when the stream continues it)."""
        loop = asyncio.get_running_loop()
        cfg = await self._read_config()
        if cfg is None:
            await asyncio.sleep(0.5)  # the map's primary has not made its log yet
            return
        self._use_config(cfg)
        si = await self.link.js.stream_info(self.stream)
        first = int(si.state.first_seq or 1)  # the oldest stream seq still held
        if self.base == 0 and first <= 1:
            await loop.run_in_executor(None, lambda: self.server.run_in_worker(
                lambda: self._new_state(None), timeout_s=300.0))
            return
        blob = await self._download()
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
        return _pack({"seq": st.seq, "digest": st.digest(), "verdicts": dict(st.verdicts),
                          "state": encode_snapshot(st.map.snapshot()), "ids": st.export_ids(),
                          "deferral": None if st.deferral is None else st.deferral.state.encode()})

    async def _upload(self, blob: bytes) -> None:
        await self.link.snaps.put(self.lease_key, blob)

    async def _download(self) -> bytes | None:
        from nats.js.errors import ObjectNotFoundError

        try:
            res = await self.link.snaps.get(self.lease_key)
        except ObjectNotFoundError:
            return None
        return bytes(res.data)

    def snapshot_soon(self) -> None:
        """On the worker, after an input at a ``--disk-snapshot-every`` seq: upload a
        snapshot for late standbys (one at a time; skipped while one is uploading)."""
        if self._snap_busy or self.st is None:
            return
        self._snap_busy = True
        blob = self._snapshot_blob(self.st)

        async def up() -> None:
            try:
                await self._upload(blob)
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
                      gate_defer=DeferOptions.from_dict(cfg.get("gate_defer")))
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
            ack = st.apply(e.op, req, time_ns=e.recv_ns)
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

    def append(self, st: MapState, e: Entry) -> tuple[int, bool]:
        """On the worker, for an input just applied to ``st`` (seq ``e.seq``): put it in the
        log. Returns (its map seq, whether this server stored it: False for a duplicate id
        already in the log from before).

        Raises
        ------
        Refused
            The log refused it or could not be reached before the lease could expire: the
            state now holds an input the log may not (``dirty``).
        """
        expected = e.seq - 1 - self.base
        data = pack_entry(e.seq, e.op, e.recv_ns, e.sender, e.request_id, e.payload,
                          e.digest)
        deadline = max(self.valid_until, time.monotonic()) + 0.05
        try:
            return self.link.run(self._publish(data, e.request_id, expected, deadline),
                                 timeout_s=deadline - time.monotonic() + 2 * self.link.lease_ttl_s)
        except Refused:
            self.dirty = True
            raise
        except Exception as exc:
            self.dirty = True
            raise Refused(f"{type(exc).__name__}: {exc}") from None

    async def _publish(self, data: bytes, rid: str, expected: int,
                       deadline: float) -> tuple[int, bool]:
        from nats.js.errors import APIError

        hdr = {"Nats-Msg-Id": rid, "Nats-Expected-Last-Sequence": str(expected),
               "Nats-Expected-Stream": self.stream}
        tries = 0
        for _ in range(10_000):  # bounded by the deadline
            tries += 1
            t_left = deadline - time.monotonic()
            if tries > 1 and t_left <= 0:
                raise Refused(f"the log was not reached in time ({tries - 1} tries)")
            try:
                pa = await self.link.js.publish(
                    self.subject, data, timeout=max(0.05, min(self.link.opts.append_timeout_s,
                                                              t_left)),
                    headers=dict(hdr))
            except APIError as exc:
                if exc.err_code == 10071:  # wrong last sequence: another server appended
                    raise Refused(f"the log moved on: {exc.description}") from None
                if exc.code == 503 or (exc.code or 0) >= 500:
                    await asyncio.sleep(0.05)
                    continue  # no quorum now: the outcome is unknown, try again
                raise Refused(f"{exc}") from None
            except Exception as exc:  # timeout, disconnected: outcome unknown, same message
                log.info("map %r: append try %d: %s", self.name, tries, type(exc).__name__)
                await asyncio.sleep(0.05)
                continue
            seq = int(pa.seq)
            if pa.duplicate:
                if seq == expected + 1 and tries > 1:
                    return self.base + seq, True  # our own earlier try was stored
                raise Refused(f"request id {rid!r} is in the log already (seq "
                              f"{self.base + seq})")
            if seq != expected + 1:
                raise Refused(f"stored at stream seq {seq}, expected {expected + 1}")
            return self.base + seq, True
        raise Refused("too many tries")

    def _rebuild(self) -> None:
        """On the worker: the state holds an input the log refused: rebuild it from this
        server's recording (every logged input it applied, nothing else), then follow."""
        from mcsm.recording import replay

        rec = self.server.recorder
        self.st = None
        self._drop_from_server()
        if rec is None:  # no recording: start over from the log
            self.recorded = -1
            self.dirty = False
            return
        rep = replay(rec.path, from_snapshot=True, lru_size=self.server.opts.lru_size)
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

    def close(self, release: bool) -> None:
        self.stop_loop()
        try:
            self.link.run(self._close(release), 5.0)
        except Exception as exc:
            log.debug("replica close: %s", exc)

    async def _close(self, release: bool) -> None:
        await self._drop_consumer()
        if release and self.role == "primary":
            await self._release()


__all__ = ["TAKEOVER", "DEFAULT_LEASE_TTL_S", "DEFAULT_REPLICAS", "DEFAULT_LOG_MAX_BYTES",
           "DEFAULT_LOG_MAX_AGE_S", "Entry", "NatsLink", "NatsOptions", "Refused", "Replica",
           "pack_entry", "stream_name"]
