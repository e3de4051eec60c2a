"""What the replicated log relies on, checked on a real three-node JetStream cluster
(``mcsm.serve.replication``): the message id is checked before the expected last sequence, so a
retried append whose first try was stored answers ``duplicate`` with that seq (even though
the expected sequence is now stale), while another message with a stale expected sequence
is refused (code 10071), and one that expects an impossible sequence is refused naming the
stream's last (how a new primary reads the head); a lease key taken with ``create`` cannot be
taken again until it expires (the bucket's TTL), and the old holder's renewal by revision is
then refused. ``Lease.release`` deletes the lease also after a renewal whose answer it never
saw (a newer revision that still names it), and never another holder's."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path
from typing import Any

from mcsm.serve.natsrun import NatsCluster


def test_dedup_before_expected_sequence_and_lease_expiry(tmp_path: Path) -> None:
    import nats
    from nats.js.api import KeyValueConfig, StreamConfig
    from nats.js.errors import APIError, KeyNotFoundError, KeyWrongLastSequenceError

    async def run(urls: list[str]) -> None:
        nc = await nats.connect(servers=urls)
        js = nc.jetstream()
        async def elected(stream: str) -> None:
            """A new R = 3 stream (a bucket's too) elects its leader: until then a publish
            finds no responder (no publish before; a loaded host takes a while)."""
            for _ in range(400):
                if (await js.stream_info(stream)).cluster.leader:
                    return
                await asyncio.sleep(0.05)
            raise AssertionError(f"stream {stream} elected no leader in 20 s")

        await js.add_stream(StreamConfig(name="T", subjects=["t"], num_replicas=3,
                                         duplicate_window=60))
        await elected("T")

        def hdr(mid: str, last: int) -> dict[str, str]:
            return {"Nats-Msg-Id": mid, "Nats-Expected-Last-Sequence": str(last)}

        first = await js.publish("t", b"a", headers=hdr("x1", 0))
        assert first.seq == 1 and not first.duplicate
        again = await js.publish("t", b"a", headers=hdr("x1", 0))  # the retry, stale expect
        assert again.seq == 1 and again.duplicate
        try:
            await js.publish("t", b"b", headers=hdr("x2", 0))
            raise AssertionError("a stale expected sequence was accepted")
        except APIError as exc:
            assert exc.err_code == 10071
        assert (await js.publish("t", b"b", headers=hdr("x2", 1))).seq == 2
        assert (await js.stream_info("T")).state.last_seq == 2
        try:  # the head probe of MapLog.head: refused with the leader's last seq, not stored
            await js.publish("t", b"", headers={"Nats-Expected-Last-Sequence": str(1 << 62)})
            raise AssertionError("an impossible expected sequence was accepted")
        except APIError as exc:
            assert exc.err_code == 10071 and (exc.description or "").endswith(": 2"), exc
        assert (await js.stream_info("T")).state.messages == 2
        kv = await js.create_key_value(KeyValueConfig(bucket="L", ttl=1.0, history=1,
                                                      replicas=3))
        await elected("KV_L")
        rev = await kv.create("m", b"A")
        try:
            await kv.create("m", b"B")
            raise AssertionError("a held lease was taken")
        except KeyWrongLastSequenceError:
            pass
        t0 = time.monotonic()
        for _ in range(100):
            try:
                await kv.create("m", b"B")
                break
            except (KeyWrongLastSequenceError, KeyNotFoundError):  # held, or expiring now
                await asyncio.sleep(0.05)
        took = time.monotonic() - t0
        assert 0.5 < took < 4.0, took
        try:
            await kv.update("m", b"A", last=rev)
            raise AssertionError("an expired holder renewed its lease")
        except KeyWrongLastSequenceError:
            pass
        kv_r = await js.create_key_value(KeyValueConfig(bucket="R", ttl=30.0, history=1,
                                                        replicas=3))
        await elected("KV_R")
        await released(kv_r)
        await nc.close()

    async def released(kv: Any) -> None:
        from mcsm.serve.replication_lease import Lease

        a = Lease(kv, "m", "A", 30.0)
        assert await a.acquire()
        await kv.update("m", b"A", last=a.rev)  # a renewal whose answer A never saw
        await a.release()
        try:
            await kv.get("m")
            raise AssertionError("the lease was not released")
        except KeyNotFoundError:
            pass
        b = Lease(kv, "m", "B", 30.0)
        assert await b.acquire() and await a.acquire() is False
        a.rev = b.rev  # B renews: A, with a revision B wrote before, never deletes it
        await kv.update("m", b"B", last=b.rev)
        await a.release()
        assert bytes((await kv.get("m")).value) == b"B"

    with NatsCluster(tmp_path / "nats") as c:
        asyncio.run(run(c.urls))
