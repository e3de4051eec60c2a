"""One order per client, idempotency that cannot surprise, clients that survive a restart.

Real ``mcsm serve`` subprocesses on loopback: 300 pipelined "update creates f, remove f" pairs
on two keys from one client session (0 out of order); a reused request id with another
payload is refused with ``RequestIdReused``; a retry after SIGKILL + ``--restore`` is applied
once; a client streaming across SIGKILL + ``--restore`` of its server loses and doubles
nothing, and every call either succeeds or fails after its full timeout.
"""

from __future__ import annotations

import signal
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import zenoh
from mcsm import StochasticMap, wire
from mcsm.errors import McsmError, RequestIdReused
from mcsm.map import ops
from mcsm_client.client import MapClient

from tests.service.daemon_util import Daemon, noisy_at, start_daemon

N = 32


def _drain(replies: Any, deadline_s: float = 30.0) -> list[tuple[bool, bytes]]:
    out = []
    end = time.monotonic() + deadline_s
    while time.monotonic() < end:
        try:
            r = replies.recv()
        except zenoh.ZError:  # finalised
            break
        out.append((True, r.ok.payload.to_bytes()) if r.ok is not None
                   else (False, r.err.payload.to_bytes()))
    return out


def test_pipelined_update_then_remove_on_two_keys_keeps_client_order(
        tmp_path: Path, daemons: list[Daemon]) -> None:
    n = 1000  # long updates (56 KB) against tiny removes: the case that used to reorder
    d = start_daemon(tmp_path, "--samples", str(n))
    daemons.append(d)
    rng = np.random.default_rng(9101)
    pairs = 300
    with MapClient(connect=d.endpoint, timeout_s=30) as c:
        c.update("root", "base", noisy_at(rng, n, [1, 0, 0]))
        x = noisy_at(rng, n, [1, 0, 0])
        handlers = []
        for i in range(pairs):  # sent back to back, nothing awaited in between
            up = wire.encode_update(f"u{i}", "root", f"f{i}", x)
            rm = wire.encode_remove(f"r{i}", f"f{i}")
            handlers.append(("update", c.session.get(c.keys.update, payload=up, timeout=60)))
            handlers.append(("remove", c.session.get(c.keys.remove, payload=rm, timeout=60)))
        refused = []
        for _, h in handlers:
            got = _drain(h)
            assert len(got) == 1, got
            ok, data = got[0]
            if not ok:
                refused.append(type(wire.decode_error(data)).__name__)
        assert refused == []  # a remove that overtook its update would be UnknownFrame
        info = c.info()
        assert info.seq == 1 + 2 * pairs and set(info.frames) == {"root", "base"}
    assert d.stop(signal.SIGTERM) == 0, d.log_text()


def test_reused_id_with_another_payload_is_refused(tmp_path: Path,
                                                   daemons: list[Daemon]) -> None:
    d = start_daemon(tmp_path, "--samples", str(N))
    daemons.append(d)
    rng = np.random.default_rng(9102)
    x = noisy_at(rng, N, [1, 0, 0])
    with MapClient(connect=d.endpoint, timeout_s=10) as c:
        ack = c.update("a", "b", x, request_id="same-id")
        assert ack.seq == 1 and not ack.duplicate
        again = c.update("a", "b", x, request_id="same-id")  # a retry: the original ack
        assert again.duplicate and again.seq == 1
        for call in (lambda: c.update("a", "b", noisy_at(rng, N, [1, 0, 0]),
                                      request_id="same-id"),
                     lambda: c.update("a", "c", x, request_id="same-id"),
                     lambda: c.remove("b", request_id="same-id")):
            try:
                call()
            except RequestIdReused as exc:
                assert exc.fields["request_id"] == "same-id" and exc.fields["seq"] == 1
            else:
                raise AssertionError("a reused id with another payload was accepted")
        info = c.info()
        assert info.seq == 1 and set(info.frames) == {"a", "b"}
        assert info.rejected_by_error == {"RequestIdReused": 3}


def test_retry_after_sigkill_and_restore_is_applied_once(tmp_path: Path,
                                                         daemons: list[Daemon]) -> None:
    d1 = start_daemon(tmp_path, "--samples", str(N), name="first")
    daemons.append(d1)
    rng = np.random.default_rng(9103)
    ops = [("w", f"p{i}", noisy_at(rng, N, [1, 0, 0])) for i in range(5)]
    with MapClient(connect=d1.endpoint, timeout_s=20) as c:
        acks = [c.update(a, b, x, request_id=f"k{i}") for i, (a, b, x) in enumerate(ops)]
        first_server = c.server_id
        d1.proc.send_signal(signal.SIGKILL)
        d1.proc.wait(timeout=10)
        d2 = start_daemon(tmp_path, "--restore", str(d1.record), name="second",
                          listen_on=d1.endpoint)
        daemons.append(d2)
        # the same client session retries the last request after the restart
        a, b, x = ops[-1]
        dup = c.update(a, b, x, request_id="k4")
        assert dup.duplicate and dup.seq == acks[-1].seq == 5
        assert c.server_id != first_server and dup.server == c.server_id
        info = c.info()
        assert info.seq == 5
        local = StochasticMap(N)
        for a, b, x in ops:
            local.update(a, b, x)
        assert info.digest == local.state_digest()


def test_client_streams_across_sigkill_and_restore(tmp_path: Path,
                                                   daemons: list[Daemon]) -> None:
    """Every call succeeds or fails only after its full timeout; none lost, none doubled."""
    d1 = start_daemon(tmp_path, "--samples", str(N), name="first")
    daemons.append(d1)
    rng = np.random.default_rng(9104)
    ops = [(f"p{i}", f"p{i + 1}", noisy_at(rng, N, [1, 0, 0])) for i in range(120)]
    timeout_s = 30.0
    acks: list[wire.Ack] = []
    failures: list[tuple[float, Exception]] = []
    durations: list[float] = []

    def stream(c: MapClient) -> None:
        for i, (a, b, x) in enumerate(ops):
            t0 = time.monotonic()
            try:
                acks.append(c.update(a, b, x, request_id=f"s{i}"))
            except McsmError as exc:
                failures.append((time.monotonic() - t0, exc))
                return
            durations.append(time.monotonic() - t0)

    with MapClient(connect=d1.endpoint, timeout_s=timeout_s) as c:
        t = threading.Thread(target=stream, args=(c,))
        t.start()
        deadline = time.monotonic() + 30
        while len(acks) < 20 and time.monotonic() < deadline and t.is_alive():
            time.sleep(0.01)  # polling the ack count
        assert len(acks) >= 20, failures
        d1.proc.send_signal(signal.SIGKILL)
        d1.proc.wait(timeout=10)
        killed_at = len(acks)
        d2 = start_daemon(tmp_path, "--restore", str(d1.record), name="second",
                          listen_on=d1.endpoint)
        daemons.append(d2)
        t.join(timeout=120)
        assert not t.is_alive()
        assert not failures, failures
        assert killed_at < len(ops), "the stream finished before the kill"
        assert [a.seq for a in acks] == list(range(1, len(ops) + 1))
        info = c.info()
        assert info.seq == len(ops)
        local = StochasticMap(N)
        for a, b, x in ops:
            local.update(a, b, x)
        assert info.digest == local.state_digest()
    # the longest call is the one that waited through the restart, within its timeout
    assert 0.5 < max(durations) < timeout_s
    assert d2.stop(signal.SIGTERM) == 0, d2.log_text()


def test_id_memory_is_bounded_by_time_and_count() -> None:
    """Ids are forgotten after id_ttl_s (receive times, so a replayed memory ages the same
    way) and beyond lru_size; a remembered id with another request raises RequestIdReused."""
    from mcsm.log.topics import decode_input
    from mcsm.map.state import DEFAULT_ID_TTL_S, DEFAULT_LRU, MapState

    assert DEFAULT_ID_TTL_S >= 300 and DEFAULT_LRU >= 100_000
    rng = np.random.default_rng(9105)
    st = MapState("m", StochasticMap(N), lru_size=3, id_ttl_s=60.0)

    def up(rid: str, b: str) -> Any:
        x = noisy_at(rng, N, [1, 0, 0])
        return decode_input("update", wire.encode_update(rid, "w", b, x), N)

    t0 = 1_000_000_000_000
    reqs = {f"i{k}": up(f"i{k}", f"f{k}") for k in range(4)}
    for k, req in enumerate(reqs.values()):
        st.apply("update", req, time_ns=t0 + k * 10**9)
    fp = {rid: ops.fingerprint("update", r) for rid, r in reqs.items()}
    now = t0 + 4 * 10**9
    assert st.lookup("i0", fp["i0"], now) is None  # beyond the count of 3
    dup = st.lookup("i1", fp["i1"], now)
    assert dup is not None and dup.duplicate and dup.seq == 2
    try:
        st.lookup("i1", fp["i2"], now)
    except RequestIdReused:
        pass
    else:
        raise AssertionError("another request under a remembered id was not refused")
    assert st.lookup("i3", fp["i3"], t0 + 3 * 10**9 + 59 * 10**9) is not None
    assert st.lookup("i3", fp["i3"], t0 + 3 * 10**9 + 61 * 10**9) is None  # older than 60 s


def test_replies_and_events_are_labelled_msgpack(tmp_path: Path,
                                                 daemons: list[Daemon]) -> None:
    d = start_daemon(tmp_path, "--samples", str(N))
    daemons.append(d)
    rng = np.random.default_rng(9106)
    with MapClient(connect=d.endpoint, timeout_s=10) as c:
        with c.session.declare_subscriber(c.keys.events) as sub:
            ok = list(c.session.get(c.keys.info, payload=wire.encode_info("e1"), timeout=5))
            err = list(c.session.get(c.keys.query, payload=b"junk", timeout=5))
            c.update("a", "b", noisy_at(rng, N, [1, 0, 0]))
            sample = None
            deadline = time.monotonic() + 10
            while sample is None and time.monotonic() < deadline:
                sample = sub.try_recv()
                if sample is None:
                    time.sleep(0.01)  # polling the subscriber's channel
    assert sample is not None
    assert len(ok) == 1 and str(ok[0].ok.encoding) == wire.ENCODING == "application/msgpack"
    assert len(err) == 1 and str(err[0].err.encoding) == "application/msgpack"
    assert str(sample.encoding) == "application/msgpack"
