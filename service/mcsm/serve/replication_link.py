"""A server's connection to the NATS JetStream cluster that holds its replicated maps' logs
(:mod:`mcsm.serve.replication`): the options of ``mcsm serve --nats``, the connection on its own
asyncio thread, the fleet's buckets (the leases, the maps' configs, the snapshots) and the
names every map's stream, subject and keys get in NATS.

Imported only by a server with ``--nats`` (nats-py is imported when the link starts).
"""

from __future__ import annotations

import asyncio
import json
import logging
import re
import threading
import time
from collections.abc import Awaitable, Callable, Coroutine
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

from mcsm.errors import McsmError
from mcsm.serve.replication_defaults import (
    DEFAULT_LEASE_TTL_S,
    DEFAULT_LOG_MAX_AGE_S,
    DEFAULT_LOG_MAX_BYTES,
    DEFAULT_REPLICAS,
)

log = logging.getLogger(__name__)
T = TypeVar("T")

LEASE_BUCKET = "MCSM_LEASE"
"""The KV bucket of the maps' leases (its entries expire after the lease TTL)."""
MAPS_BUCKET = "MCSM_MAPS"
"""The KV bucket of each replicated map's config (options, base seq, checkpoint periods)."""
SNAP_BUCKET = "MCSM_SNAP"
"""The object store of each map's latest snapshot (for late standbys)."""


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


async def retry(what: str, make: Callable[[], Awaitable[T]], deadline: float) -> T:
    """``await make()``, again after each failure until ``deadline`` (monotonic), for the
    idempotent steps of starting (opening buckets, making a map's stream): several servers
    starting at once, or a cluster electing leaders, answer some of them late.

    Raises
    ------
    McsmError
        At once if ``make`` raised one (a refusal, not a transient failure).
    Exception
        ``make``'s last error once ``deadline`` passed.
    """
    for attempt in range(1, 1_000_000):  # bounded by the deadline
        try:
            return await make()
        except McsmError:
            raise
        except Exception as exc:
            if time.monotonic() > deadline:
                raise
            log.warning("nats: %s, try %d: %s: %s; again", what, attempt, type(exc).__name__,
                        exc)
            await asyncio.sleep(min(0.5, 0.05 * attempt))
    raise McsmError(f"nats: {what}: too many tries")


def nats_name(text: str) -> str:
    """A name for NATS (streams, subjects, keys): ``[A-Za-z0-9-]`` kept, the rest ``_xx``."""
    return re.sub(r"[^A-Za-z0-9-]", lambda m: f"_{ord(m.group()):02x}", text)


def stream_name(prefix: str, map_name: str) -> str:
    """The stream of a map's log."""
    return f"MCSM_{nats_name(prefix)}_{nats_name(map_name)}"


def map_key(prefix: str, map_name: str) -> str:
    """The map's key in the lease and config buckets and the snapshot store."""
    return f"{nats_name(prefix)}.{nats_name(map_name)}"


def map_subject(prefix: str, map_name: str) -> str:
    """The subject the map's inputs are published on (its stream's only subject)."""
    return f"mcsm.{nats_name(prefix)}.{nats_name(map_name)}"


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
            self.run(self._connect(timeout_s - 1.0), timeout_s)
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

    async def _connect(self, timeout_s: float) -> None:
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
        deadline = time.monotonic() + timeout_s
        self.leases = await retry("the lease bucket", lambda: self._bucket(KeyValueConfig(
            bucket=LEASE_BUCKET, history=1, ttl=float(o.lease_ttl_s), replicas=r)), deadline)
        self.maps = await retry("the config bucket", lambda: self._bucket(KeyValueConfig(
            bucket=MAPS_BUCKET, history=1, replicas=r)), deadline)
        self.snaps = await retry("the snapshot store", lambda: self._store(
            ObjectStoreConfig(replicas=r)), deadline)
        info = await retry("the lease bucket's TTL", lambda: self.js.stream_info(
            f"KV_{LEASE_BUCKET}"), deadline)
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

    async def _store(self, cfg: Any) -> Any:
        try:
            return await self.js.create_object_store(SNAP_BUCKET, config=cfg)
        except Exception:  # made by another server with other settings: use it as it is
            return await self.js.object_store(SNAP_BUCKET)

    def close(self) -> None:
        if self.nc is not None:
            try:
                self.run(self.nc.close(), 5.0)
            except Exception as exc:  # already gone
                log.debug("nats close: %s", exc)
        if self.loop.is_running():
            self.loop.call_soon_threadsafe(self.loop.stop)
            self._thread.join(timeout=5.0)


__all__ = ["LEASE_BUCKET", "MAPS_BUCKET", "SNAP_BUCKET", "NatsLink", "NatsOptions", "map_key",
           "map_subject", "nats_name", "retry", "stream_name"]
