"""A replicated map's log in NATS JetStream (:mod:`mcsm.serve.replication`): the entry codec, and
the stream, config, snapshot and consumer operations of one map.

* **Entries.** One stream message per applied input: its recording record (operation, receive
  time, sender, request id, request bytes, and the digest at checkpoints), msgpack with the
  wire version, so a standby rebuilds the map exactly as replay does and carries any
  operation of :data:`mcsm.log.topics.INPUT_TOPICS` without knowing which.
* **Appends** are fenced: ``Nats-Expected-Last-Sequence`` is the stream seq the appender has
  applied, ``Nats-Msg-Id`` the request id (de-duplication window ``--id-ttl-s``). JetStream
  checks the id before the expected sequence (``tests/service/test_nats_log.py``), so an
  append whose outcome is unknown is resolved by sending it again unchanged.
* **Consumers.** A standby reads the stream through an ephemeral pull consumer, in batches of
  :data:`FETCH_BATCH` (its memory bound), described ``standby <server id>`` so the primary can
  list its standbys.
* **Config and snapshots.** The map's config (options, base seq, checkpoint periods) is a key
  in ``MCSM_MAPS``; its latest snapshot (for late standbys) an object in ``MCSM_SNAP``.

Every coroutine here runs on the link's loop (:class:`mcsm.serve.replication_link.NatsLink`).
"""

from __future__ import annotations

import asyncio
import logging
import re
import time
from dataclasses import dataclass
from typing import Any

from mcsm import wire
from mcsm.errors import BadMessage
from mcsm.log.topics import INPUT_TOPICS
from mcsm.serve.replication_link import NatsLink, map_key, map_subject, stream_name

log = logging.getLogger(__name__)

FETCH_BATCH = 32
"""Inputs a standby fetches at once (its memory bound: this many inputs of at most 8 MiB)."""
_MAX_MSG = 64 * 1024 * 1024
_NEVER = 1 << 62  # an expected last sequence no stream reaches
WRONG_LAST_SEQUENCE = 10071
"""JetStream's error code for an append whose expected last sequence is not the stream's."""
ID_IN_PROCESS = 10158
"""JetStream's error code for a message id whose earlier append is still being stored (its
outcome is not known yet: the append is tried again)."""


def pack_obj(obj: dict[str, Any]) -> bytes:
    """``obj`` as msgpack with the wire version (configs, snapshots)."""
    return wire.pack({"v": wire.VERSION, **obj})


def pack_entry(seq: int, op: str, recv_ns: int, sender: str, request_id: str, payload: bytes,
               digest: str | None) -> bytes:
    """One logged input as a stream message."""
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

    def pack(self) -> bytes:
        return pack_entry(self.seq, self.op, self.recv_ns, self.sender, self.request_id,
                          self.payload, self.digest)

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


class MapLog:
    """One map's stream, config and snapshot in JetStream, and this server's consumer of it.
    Stream seqs here; the replica adds the map's base seq."""

    def __init__(self, link: NatsLink, prefix: str, name: str) -> None:
        self.link, self.name = link, name
        self.stream = stream_name(prefix, name)
        self.subject = map_subject(prefix, name)
        self.key = map_key(prefix, name)
        self._sub: Any = None
        self._consumers = 0

    # ------------------------------------------------------------ the stream and its config
    async def create(self, config: dict[str, Any], id_ttl_s: float) -> None:
        """Make the stream (R = ``--replicas``, retention ``--log-max-bytes/-age``,
        de-duplication window ``id_ttl_s``) and the map's config, unless another server
        made the config first."""
        from nats.js.api import DiscardPolicy, StorageType, StreamConfig
        from nats.js.errors import KeyWrongLastSequenceError

        o = self.link.opts
        await self.link.js.add_stream(StreamConfig(
            name=self.stream, subjects=[self.subject], num_replicas=max(1, o.replicas),
            storage=StorageType.FILE, discard=DiscardPolicy.OLD,
            max_bytes=int(o.max_bytes) if o.max_bytes > 0 else None,
            max_age=float(o.max_age_s) if o.max_age_s > 0 else None,
            duplicate_window=max(1.0, float(id_ttl_s)), allow_direct=True,
            max_msg_size=min(16 << 20, int(o.max_bytes)) if o.max_bytes > 0 else 16 << 20))
        try:
            await self.link.maps.create(self.key, pack_obj(config))
        except KeyWrongLastSequenceError:
            pass  # another server made it meanwhile: use its

    async def read_config(self) -> dict[str, Any] | None:
        """The map's config, None if no server made its log yet."""
        from nats.js.errors import KeyNotFoundError

        try:
            e = await self.link.maps.get(self.key)
        except KeyNotFoundError:
            return None
        return dict(wire.unpack(bytes(e.value), max_bytes=1 << 20, max_map_len=64))

    async def bounds(self) -> tuple[int, int]:
        """(the oldest stream seq still held, the last stream seq), from stream info: a hint
        only, since while the stream has no leader a lagging replica may answer (use
        :meth:`head` where it matters)."""
        si = await self.link.js.stream_info(self.stream)
        return int(si.state.first_seq or 1), int(si.state.last_seq or 0)

    async def head(self, timeout_s: float = 1.0) -> int:
        """The last stream seq as the stream's leader sees it, the way every append is
        fenced: an append that expects an impossible last sequence is refused with the
        leader's own (error 10071, "wrong last sequence: N"); nothing is stored. Without a
        leader there is no answer (an exception: try again).

        Raises
        ------
        Refused
            If the answer is not that refusal.
        """
        from nats.js.errors import APIError

        try:
            await self.link.js.publish(self.subject, b"", timeout=timeout_s, headers={
                "Nats-Expected-Last-Sequence": str(_NEVER), "Nats-Expected-Stream": self.stream})
        except APIError as exc:
            m = re.search(r"(\d+)\s*$", exc.description or "")
            if exc.err_code == WRONG_LAST_SEQUENCE and m is not None:
                return int(m.group(1))
            raise Refused(f"the log's head: {exc}") from None
        raise Refused("the log stored a probe of its head")  # not possible: never expected

    # ------------------------------------------------------------ appends
    async def publish(self, data: bytes, rid: str, expected: int, deadline: float) -> int:
        """Append one entry after stream seq ``expected``, trying until ``deadline``
        (monotonic) while the outcome is unknown; returns its stream seq.

        Raises
        ------
        Refused
            Another server appended (wrong last sequence), the id is in the log from another
            append, or the log gave no answer before ``deadline``.
        """
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
                if exc.err_code == WRONG_LAST_SEQUENCE:
                    raise Refused(f"the log moved on: {exc.description}") from None
                if (exc.code or 0) >= 500 or exc.err_code == ID_IN_PROCESS:
                    await asyncio.sleep(0.05)
                    continue  # no quorum now, or our first try in flight: try again
                raise Refused(f"{exc}") from None
            except Exception as exc:  # timeout, disconnected: outcome unknown, same message
                log.info("map %r: append try %d: %s", self.name, tries, type(exc).__name__)
                await asyncio.sleep(0.05)
                continue
            seq = int(pa.seq)
            if pa.duplicate:
                if seq == expected + 1 and tries > 1:
                    return seq  # our own earlier try was stored
                raise Refused(f"request id {rid!r} is in the log already (stream seq {seq})")
            if seq != expected + 1:
                raise Refused(f"stored at stream seq {seq}, expected {expected + 1}")
            return seq
        raise Refused("too many tries")

    # ------------------------------------------------------------ this server's consumer
    @property
    def following(self) -> bool:
        return self._sub is not None

    def _consumer_name(self) -> str:
        return f"sb-{self.link.server_id}-{self._consumers}"

    async def follow(self, start: int) -> None:
        """(Re)make this server's consumer, delivering from stream seq ``start``."""
        from nats.js.api import AckPolicy, ConsumerConfig, DeliverPolicy

        await self.unfollow()
        self._consumers += 1
        name = self._consumer_name()
        await self.link.js.add_consumer(self.stream, ConsumerConfig(
            name=name, description=f"standby {self.link.server_id}",
            deliver_policy=DeliverPolicy.BY_START_SEQUENCE, opt_start_seq=max(1, start),
            ack_policy=AckPolicy.NONE, inactive_threshold=10.0, mem_storage=True,
            num_replicas=1))
        self._sub = await self.link.js.pull_subscribe_bind(
            consumer=name, stream=self.stream, pending_msgs_limit=4 * FETCH_BATCH,
            pending_bytes_limit=4 * FETCH_BATCH * 9 * 1024 * 1024)

    async def fetch(self, timeout_s: float = 0.25) -> list[tuple[int, Entry]]:
        """At most :data:`FETCH_BATCH` next entries with their stream seqs ([] if none came
        within ``timeout_s``)."""
        try:
            msgs = await self._sub.fetch(FETCH_BATCH, timeout=timeout_s)
        except TimeoutError:
            return []
        return [(int(m.metadata.sequence.stream), Entry.unpack(m.data)) for m in msgs]

    async def unfollow(self) -> None:
        sub, self._sub = self._sub, None
        if sub is None:
            return
        try:
            await sub.unsubscribe()
            await asyncio.wait_for(self.link.js.delete_consumer(self.stream,
                                                                self._consumer_name()), 1.0)
        except Exception as exc:  # gone already; it expires when inactive
            log.debug("consumer: %s", exc)

    async def describe_consumer(self) -> str:
        """This server's consumer as the cluster sees it (for the log)."""
        try:
            ci = await asyncio.wait_for(self.link.js.consumer_info(
                self.stream, self._consumer_name()), 1.0)
        except Exception as exc:
            return f"{self._consumer_name()}: {type(exc).__name__}: {exc}"
        cl = ci.cluster
        return (f"{ci.name}: delivered {ci.delivered.stream_seq if ci.delivered else None}, "
                f"pending {ci.num_pending}, waiting {ci.num_waiting}, on "
                f"{cl.leader if cl is not None else '?'}")

    async def standbys(self) -> dict[str, int]:
        """For the primary: each standby's server id -> the last stream seq the log delivered
        to it. A standby may have older consumers too, not yet expired (ones it could not
        delete while cut off): its newest one (``sb-<server id>-<k>``, the highest k)
        counts. This server's own consumers, left from when it was a standby, are not
        listed, and are deleted."""
        newest: dict[str, tuple[int, int]] = {}
        mine: list[str] = []
        for ci in await asyncio.wait_for(self.link.js.consumers_info(self.stream), 2.0):
            desc = ci.config.description or ""
            if not desc.startswith("standby ") or ci.delivered is None:
                continue
            sid, tail = desc[8:], (ci.name or "").rsplit("-", 1)[-1]
            if sid == self.link.server_id:
                mine.append(ci.name)
                continue
            k = int(tail) if tail.isdigit() else 0
            if k >= newest.get(sid, (-1, 0))[0]:
                newest[sid] = (k, int(ci.delivered.stream_seq or 0))
        for name in mine:
            try:
                await asyncio.wait_for(self.link.js.delete_consumer(self.stream, name), 1.0)
            except Exception as exc:  # it expires when inactive
                log.debug("consumer %s: %s", name, exc)
        return {sid: seq for sid, (_, seq) in newest.items()}

    # ------------------------------------------------------------ snapshots
    async def upload(self, blob: bytes) -> None:
        await self.link.snaps.put(self.key, blob)

    async def download(self) -> bytes | None:
        """The latest snapshot, None if there is none."""
        from nats.js.errors import ObjectNotFoundError

        try:
            res = await self.link.snaps.get(self.key)
        except ObjectNotFoundError:
            return None
        return bytes(res.data)


__all__ = ["FETCH_BATCH", "ID_IN_PROCESS", "WRONG_LAST_SEQUENCE", "Entry", "MapLog", "Refused",
           "pack_entry", "pack_obj"]
