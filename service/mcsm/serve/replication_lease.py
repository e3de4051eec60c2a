"""A replicated map's lease (:mod:`mcsm.serve.replication`): which server may append to the map's
log and acknowledge its inputs.

One key per map in the KV bucket ``MCSM_LEASE``, whose entries expire after the lease TTL
(``--lease-ttl``; the bucket's ``max_age``). A server takes the lease with compare-and-set
(``create``: only if the key is absent), renews it with compare-and-set on the revision it
wrote (``update``), every TTL/6, and deletes it (by revision) when it stops gracefully.

**Validity.** The server counts the lease valid until ``t_sent + VALID_FRACTION * TTL``,
``t_sent`` being the monotonic time it *sent* the successful create or renewal: JetStream
stamps the entry at ``t_stored >= t_sent`` and keeps it until ``t_stored + TTL`` at least, so
no other server can create the key before the holder's validity ends; the remaining
``(1 - VALID_FRACTION) * TTL`` covers the stamping delay and timer slack (one machine's clock
here; across machines, their drift over one TTL). A renewal whose outcome is unknown
(timeout, no quorum) is not a renewal: the validity runs out unless a later one succeeds.
"""

from __future__ import annotations

import asyncio
import logging
import time
from typing import Any

log = logging.getLogger(__name__)

VALID_FRACTION = 0.75
"""A holder acknowledges until ``t_sent + VALID_FRACTION * TTL``."""
RENEW_FRACTION = 1.0 / 6.0
"""A holder renews every ``RENEW_FRACTION * TTL``."""
RETRY_FRACTION = 1.0 / 20.0
"""After a renewal without an answer, the next try comes ``RETRY_FRACTION * TTL`` later."""


class Lease:
    """One map's lease as one server sees it. Methods are coroutines of the link's loop;
    :meth:`valid` may be called from any thread."""

    def __init__(self, kv: Any, key: str, holder: str, ttl_s: float) -> None:
        self.kv, self.key, self.holder, self.ttl_s = kv, key, holder, float(ttl_s)
        self.rev = 0  # the revision this server last wrote
        self.term = 0  # the revision when this server took it (info.epoch)
        self.holding = False  # this server took it and has not seen it lost
        self.renew_at = 0.0
        self.valid_until = 0.0

    def valid(self) -> bool:
        """Whether this server may acknowledge now (no other server can hold the lease)."""
        return time.monotonic() < self.valid_until

    def _granted(self, t_sent: float, rev: int) -> None:
        self.rev = int(rev)
        self.holding = True
        self.valid_until = t_sent + VALID_FRACTION * self.ttl_s
        self.renew_at = t_sent + RENEW_FRACTION * self.ttl_s

    def _lost(self) -> None:
        self.holding = False
        self.valid_until = 0.0

    async def acquire(self) -> bool:
        """Take the lease if no one holds it; False if held (or expiring as we looked). A
        lease that holds this server's id is this server's (an earlier try whose answer was
        lost made it): it is renewed by its revision and kept."""
        from nats.js.errors import KeyNotFoundError, KeyWrongLastSequenceError

        t0 = time.monotonic()
        try:
            rev = await asyncio.wait_for(self.kv.create(self.key, self.holder.encode()),
                                         self.ttl_s / 2)
        except KeyNotFoundError:
            return False
        except KeyWrongLastSequenceError:
            try:
                e = await asyncio.wait_for(self.kv.get(self.key), self.ttl_s / 4)
            except KeyNotFoundError:
                return False
            if bytes(e.value or b"") != self.holder.encode():
                return False
            self.rev = self.term = int(e.revision or 0)
            return await self.renew() is True
        self._granted(t0, rev)
        self.term = self.rev
        return True

    async def try_take(self) -> bool:
        """Take the lease if it looks free (a cheap read first, then :meth:`acquire`)."""
        from nats.js.errors import KeyNotFoundError

        try:
            await asyncio.wait_for(self.kv.get(self.key), 1.0)
            return False  # held
        except KeyNotFoundError:
            pass  # free: never taken, expired or deleted
        return await self.acquire()

    async def renew(self) -> bool | None:
        """True: renewed; False: lost (another holds it, or it expired); None: unknown (no
        answer in time: the validity keeps running out)."""
        from nats.js.errors import KeyWrongLastSequenceError

        t0 = time.monotonic()
        try:
            rev = await asyncio.wait_for(self.kv.update(self.key, self.holder.encode(),
                                                        last=self.rev), self.ttl_s / 4)
        except KeyWrongLastSequenceError:
            self._lost()
            return False
        except Exception as exc:  # timeout, no quorum, disconnected: try again soon
            log.info("lease %s: renewal: %s", self.key, type(exc).__name__)
            self.renew_at = time.monotonic() + RETRY_FRACTION * self.ttl_s
            return None
        self._granted(t0, rev)
        return True

    async def release(self) -> None:
        """Delete the lease (by revision, so never another holder's); it expires by itself
        if that fails. A renewal cancelled in flight (the server stopping) or whose answer
        was lost may have written a newer revision: when the entry still names this server,
        it is deleted by that revision."""
        rev = self.rev
        for _ in range(2):
            try:
                await asyncio.wait_for(self.kv.delete(self.key, last=rev), 2.0)
                break
            except Exception as exc:  # expired already, renewed meanwhile, or unreachable
                newer = await self._own_revision()
                if newer is None or newer == rev:
                    log.info("lease %s: not released: %s", self.key, exc)
                    break
                rev = newer
        self._lost()

    async def _own_revision(self) -> int | None:
        """The lease entry's revision if it names this server (None otherwise)."""
        try:
            e = await asyncio.wait_for(self.kv.get(self.key), 1.0)
        except Exception:
            return None
        if bytes(e.value or b"") != self.holder.encode():
            return None
        return int(e.revision or 0)

    async def holder_now(self) -> str:
        """The id of the server that holds it now ("?" if unknown)."""
        try:
            return bytes((await self.kv.get(self.key)).value).decode()
        except Exception:
            return "?"


__all__ = ["RENEW_FRACTION", "RETRY_FRACTION", "VALID_FRACTION", "Lease"]
