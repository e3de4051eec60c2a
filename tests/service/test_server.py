"""The daemon as a real subprocess over real Zenoh sessions on loopback.

Checked against the same operations applied in-process with ``StochasticMap``: acks, query
samples (bit-exact), digests; malformed payloads get typed errors and change neither the map
nor the recording; retried ids are not applied twice; SIGKILL loses no acknowledged update.
"""

from __future__ import annotations

import json
import signal
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh
from mcsm import StochasticMap, wire
from mcsm.cli import main as mcsm_main
from mcsm.errors import FrameExists, McsmError, Timeout, UnknownFrame
from mcsm.recording import replay
from mcsm_client.client import MapClient

from tests.service.daemon_util import Daemon, free_port, noisy_at, start_daemon
from tests.wire_cases import CASES

N = 32


def scenario(rng: np.random.Generator, n: int) -> list[tuple[str, str, str, np.ndarray | None]]:
    """Every kind of operation: new component, new frame, point, loop closures, join, remove."""
    p = np.array([2.0, 1.0, 0.0]) + 0.05 * rng.standard_normal((n, 3))
    return [
        ("update", "w", "r0", noisy_at(rng, n, [1, 0, 0])),
        ("update", "r0", "r1", noisy_at(rng, n, [1, 0, 0], yaw=0.1)),
        ("point", "r1", "lm0", p),
        ("update", "w", "r1", noisy_at(rng, n, [2, 0.1, 0], yaw=0.1)),
        ("update", "a", "b", noisy_at(rng, n, [0, 1, 0])),
        ("update", "r1", "a", noisy_at(rng, n, [0, 0, 1])),
        ("point", "r0", "lm0", np.array([3.0, 1.0, 0.0]) + 0.05 * rng.standard_normal((n, 3))),
        ("remove", "r0", "", None),
        ("update", "b", "c", noisy_at(rng, n, [1, 1, 0])),
    ]


def apply_local(m: StochasticMap, op: str, a: str, b: str, x: np.ndarray | None) -> Any:
    if op == "remove":
        return m.remove(a)
    assert x is not None
    return m.update(a, b, x)


def apply_remote(c: MapClient, op: str, a: str, b: str, x: np.ndarray | None,
                 request_id: str | None = None) -> wire.Ack:
    if op == "remove":
        return c.remove(a, request_id=request_id)
    if op == "point":
        return c.update_point(a, b, x, request_id=request_id)
    return c.update(a, b, x, request_id=request_id)


def raw_call(session: zenoh.Session, key: str, payload: bytes,
             timeout_s: float = 5.0) -> tuple[bool, bytes]:
    """One get; exactly one reply expected (ok or mcsm error)."""
    got = []
    for reply in session.get(key, payload=payload, timeout=timeout_s):
        got.append((True, reply.ok.payload.to_bytes()) if reply.ok is not None
                   else (False, reply.err.payload.to_bytes()))
    assert len(got) == 1, got
    return got[0]


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Any:
    work = tmp_path_factory.mktemp("srv")
    d = start_daemon(work, "--samples", str(N), "--checkpoint-every", "4", "--map", "main",
                     "--map", "table", "--map", "ev", "--map", "a", "--map", "b",
                     "--map", "conc")
    yield d
    code = d.stop(signal.SIGTERM)
    assert code == 0, d.log_text()


def test_stream_matches_in_process_and_replay(server: Daemon) -> None:
    rng = np.random.default_rng(4401)
    ops = scenario(rng, N)
    local = StochasticMap(N)
    with MapClient(map="main", connect=server.endpoint, timeout_s=10) as c:
        kinds = set()
        for i, (op, a, b, x) in enumerate(ops, start=1):
            ack = apply_remote(c, op, a, b, x)
            kinds.add(ack.kind)
            want = apply_local(local, op, a, b, x)
            assert ack.seq == i and not ack.duplicate
            assert ack.component == want.component
            if op != "remove":
                assert ack.kind == want.kind and ack.frames_added == want.frames_added
        assert kinds == {"new_component", "new_frame", "loop_closure", "join", "remove"}
        for a, b in (("w", "lm0"), ("w", "c"), ("lm0", "a"), ("c", "w")):
            got = c.query(a, b)
            assert got.tobytes() == local.query(a, b).tobytes()
            mean, cov = c.marginal(a, b)
            want_mean, want_cov = local.marginal(a, b)
            assert mean.tobytes() == want_mean.tobytes() and cov.tobytes() == want_cov.tobytes()
        info = c.info()
        assert info.digest == local.state_digest()
        assert info.seq == len(ops) and set(info.frames) == set(local.frames())
        assert info.components == {r: tuple(local.component(r)) for r in local.components()}
        assert info.recording == str(server.record)
    # the live recording, read while the server runs, replays to the live digest
    rep = replay(server.record)
    assert rep.identical, rep.divergence
    assert rep.states["main"].map.state_digest() == local.state_digest()
    assert rep.checkpoints_ok >= 2  # checkpoint every 4 operations


@pytest.mark.parametrize("case_id,op,build,error,map_level", CASES, ids=[c[0] for c in CASES])
def test_malformed_payloads_get_typed_errors_and_change_nothing(
        server: Daemon, case_id: str, op: str, build: Any, error: str, map_level: bool) -> None:
    rng = np.random.default_rng(4402)
    with MapClient(map="table", connect=server.endpoint, timeout_s=10) as c:
        if "w" not in c.info().frames:
            c.update("w", "r", noisy_at(rng, N, [1, 0, 0]))
            c.update("lonely", "lonely2", noisy_at(rng, N, [0, 1, 0]))
        before = c.info()
        size_before = server.record.stat().st_size
        ok, payload = raw_call(c.session, getattr(c.keys, op), build(N))
        assert not ok, f"{case_id} was accepted"
        err = wire.decode_error(payload)
        assert type(err).__name__ == error, err
        after = c.info()
    assert (after.seq, after.digest, after.frames) == (before.seq, before.digest, before.frames)
    assert after.rejected == before.rejected + 1
    assert after.rejected_by_error.get(error, 0) == before.rejected_by_error.get(error, 0) + 1
    assert server.record.stat().st_size == size_before  # nothing recorded


def test_retried_request_id_returns_the_original_ack(server: Daemon) -> None:
    rng = np.random.default_rng(4403)
    with MapClient(map="table", connect=server.endpoint, timeout_s=10) as c:
        x = noisy_at(rng, N, [5, 0, 0])
        first = c.update("dup0", "dup1", x, request_id="retry-me")
        seq_after_first = c.info().seq
        again = c.update("dup0", "dup1", x, request_id="retry-me")
        info = c.info()
    assert again.duplicate and not first.duplicate
    assert (again.seq, again.kind, again.component) == (first.seq, first.kind, first.component)
    assert info.seq == seq_after_first


def test_events_follow_applied_operations(server: Daemon) -> None:
    rng = np.random.default_rng(4404)
    with MapClient(map="ev", connect=server.endpoint, timeout_s=10) as c:
        with c.watch() as stream:
            acks = [c.update("e0", "e1", noisy_at(rng, N, [1, 0, 0])),
                    c.update("e1", "e2", noisy_at(rng, N, [1, 0, 0])),
                    c.remove("e2")]
            events = []
            deadline = time.monotonic() + 10
            while len(events) < 3 and time.monotonic() < deadline:
                ev = stream.get(0.2)
                if ev is not None:
                    events.append(ev)
    assert [e.seq for e in events] == [a.seq for a in acks] == [1, 2, 3]
    assert [e.kind for e in events] == ["new_component", "new_frame", "remove"]
    assert events[0].frames == ("e0", "e1") and events[2].frames == ("e2",)
    assert all(e.map == "ev" for e in events)


def test_submap_export_import_between_maps(server: Daemon) -> None:
    rng = np.random.default_rng(4405)
    with MapClient(map="a", connect=server.endpoint) as ca, \
            MapClient(map="b", connect=server.endpoint) as cb:
        ca.update("ra", "xa", noisy_at(rng, N, [1, 0, 0]))
        ca.update_point("xa", "pa", np.array([1.0, 2.0, 0.0]) + 0.1 * rng.standard_normal((N, 3)))
        sub = ca.export_submap("xa")
        assert sub.frames == ("ra", "xa", "pa") and sub.is_point == (False, False, True)
        ack = cb.import_submap(sub)
        assert (ack.kind, ack.frames_added) == ("import", ("ra", "xa", "pa"))
        assert cb.query("xa", "pa").tobytes() == ca.query("xa", "pa").tobytes()
        with pytest.raises(FrameExists):
            cb.import_submap(sub)
        # joining the imported component with a local one: a case I update
        cb.update("rb", "xb", noisy_at(rng, N, [0, 1, 0]))
        join = cb.update("xb", "xa", noisy_at(rng, N, [3, 0, 0]))
        assert join.kind == "join"
        assert cb.info().components.keys() == {join.component}


def test_concurrent_clients_are_serialised_by_the_worker(server: Daemon) -> None:
    """4 clients stream at once into one map: every op gets a distinct seq, and replaying the
    recording (the worker's apply order) gives the live digest."""
    per_client = 12
    acks: list[wire.Ack] = []
    errors: list[Exception] = []
    lock = threading.Lock()

    def run(k: int) -> None:
        rng = np.random.default_rng(4410 + k)
        try:
            with MapClient(map="conc", connect=server.endpoint, timeout_s=20) as c:
                for i in range(per_client):
                    # each client grows its own chain from the shared frame "hub": one component
                    a = f"c{k}_{i}" if i else "hub"
                    ack = c.update(a, f"c{k}_{i + 1}", noisy_at(rng, N, [1, 0, 0]))
                    with lock:
                        acks.append(ack)
        except McsmError as exc:
            errors.append(exc)

    threads = [threading.Thread(target=run, args=(k,)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    assert not errors and not any(t.is_alive() for t in threads)
    assert sorted(a.seq for a in acks) == list(range(1, 4 * per_client + 1))
    with MapClient(map="conc", connect=server.endpoint) as c:
        info = c.info()
    rep = replay(server.record)
    assert rep.identical
    assert rep.states["conc"].seq == info.seq == 4 * per_client
    assert rep.states["conc"].map.state_digest() == info.digest


def test_liveliness_token_names_the_server(server: Daemon) -> None:
    with MapClient(map="ev", connect=server.endpoint) as c:
        assert c.servers() == [c.info().server_id]
    with MapClient(map="nosuchmap", connect=server.endpoint) as c:
        assert c.servers(timeout_s=0.5) == []


def test_oversized_payload_is_dropped_by_zenoh_and_serving_goes_on(server: Daemon) -> None:
    with MapClient(map="table", connect=server.endpoint, timeout_s=5) as c:
        before = c.info()
        # over the 8 MiB max_message_size: the transport drops it, no mcsm reply comes back
        replies = list(c.session.get(c.keys.update, payload=b"\x00" * (9 * 1024 * 1024),
                                     timeout=1.0))
        assert all(r.ok is None for r in replies)
        after = c.info()
    assert (after.seq, after.digest) == (before.seq, before.digest)


def test_client_errors_are_typed(server: Daemon) -> None:
    with MapClient(map="main", connect=server.endpoint, timeout_s=5) as c:
        with pytest.raises(UnknownFrame, match="ghost"):
            c.query("w", "ghost")
    with MapClient(map="nosuchmap", connect=server.endpoint, timeout_s=0.3, retries=1) as c:
        t0 = time.monotonic()
        with pytest.raises(Timeout):
            c.info()
        assert time.monotonic() - t0 < 5.0


def _stream(client: MapClient, ops: list[Any], acks: list[wire.Ack], errors: list[Exception],
            stop: threading.Event) -> None:
    for i, (op, a, b, x) in enumerate(ops):
        if stop.is_set():
            return
        try:
            acks.append(apply_remote(client, op, a, b, x, request_id=f"op-{i}"))
        except (McsmError, zenoh.ZError) as exc:
            errors.append(exc)
            return


def chain_ops(rng: np.random.Generator, n: int, count: int) -> list[Any]:
    """Odometry along a chain with a loop closure back to the start every 6 steps."""
    ops: list[Any] = []
    for i in range(count):
        if i % 6 == 5:
            ops.append(("update", "p0", f"p{i}", noisy_at(rng, n, [float(i), 0, 0])))
        ops.append(("update", f"p{i}", f"p{i + 1}", noisy_at(rng, n, [1, 0, 0])))
    return ops


def test_sigkill_then_restore_keeps_every_acknowledged_update(
        tmp_path: Path, daemons: list[Daemon], capsys: pytest.CaptureFixture[str]) -> None:
    rng = np.random.default_rng(4406)
    ops = chain_ops(rng, N, 400)
    d1 = start_daemon(tmp_path, "--samples", str(N), "--checkpoint-every", "7", name="first")
    daemons.append(d1)
    acks: list[wire.Ack] = []
    errors: list[Exception] = []
    stop = threading.Event()
    with MapClient(connect=d1.endpoint, timeout_s=1.0, retries=0) as c:
        t = threading.Thread(target=_stream, args=(c, ops, acks, errors, stop))
        t.start()
        deadline = time.monotonic() + 30
        while len(acks) < 25 and time.monotonic() < deadline and t.is_alive():
            time.sleep(0.01)  # polling the ack count, not synchronising on time
        assert len(acks) >= 25, (errors, d1.log_text())
        d1.proc.send_signal(signal.SIGKILL)  # mid-stream: the client is still sending
        d1.proc.wait(timeout=10)
        t.join(timeout=30)
        stop.set()
    assert not t.is_alive()
    assert len(acks) < len(ops), "the stream finished before the kill"
    acked = len(acks)
    assert [a.seq for a in acks] == list(range(1, acked + 1))

    # the cut file replays (streaming reader), with every acknowledged input in it; replay
    # says the file is cut and exits with its own code (4), never 0
    assert mcsm_main(["replay", str(d1.record), "--no-progress"]) == 4
    out = capsys.readouterr().out
    assert "CUT" in out and "identical" not in out

    restored = d1.record.with_name("restored.mcap")
    d2 = start_daemon(tmp_path, "--restore", str(d1.record), record=restored, name="second")
    daemons.append(d2)
    with MapClient(connect=d2.endpoint, timeout_s=10) as c:
        info = c.info()
        # the update in flight at the kill may have been recorded without its ack arriving
        assert acked <= info.seq <= acked + 1
        local = StochasticMap(N)
        for op, a, b, x in ops[: info.seq]:
            apply_local(local, op, a, b, x)
        assert info.digest == local.state_digest()
        # the request-id memory survived: a retried id is not applied twice
        op, a, b, x = ops[acked - 1]
        dup = apply_remote(c, op, a, b, x, request_id=f"op-{acked - 1}")
        assert dup.duplicate and dup.seq == acked
        # and the server goes on from there
        for i in range(info.seq, info.seq + 10):
            op, a, b, x = ops[i]
            assert apply_remote(c, op, a, b, x, request_id=f"op-{i}").seq == i + 1
            apply_local(local, op, a, b, x)
        assert c.info().digest == local.state_digest()
    assert d2.stop(signal.SIGTERM) == 0, d2.log_text()
    # the new file stands on its own: it replays to the final state, checkpoints included
    rep = replay(restored)
    assert rep.identical and rep.complete, rep.divergence
    assert rep.states["default"].map.state_digest() == local.state_digest()
    assert rep.checkpoints_ok >= 3


def test_zenoh_config_file_passes_through(tmp_path: Path, daemons: list[Daemon]) -> None:
    ep = f"tcp/127.0.0.1:{free_port()}"
    conf = tmp_path / "server.json5"
    conf.write_text(json.dumps({
        "mode": "peer", "listen": {"endpoints": [ep]}, "connect": {"endpoints": []},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": {"shared_memory": {"enabled": False}}}))
    d = start_daemon(tmp_path, "--samples", "8", "--zenoh-config", str(conf), endpoint=ep)
    daemons.append(d)
    with MapClient(connect=ep, timeout_s=5) as c:
        assert c.info().n_samples == 8
    assert d.stop(signal.SIGINT) == 0
    assert replay(d.record).complete


def test_serve_refuses_an_existing_record_path(tmp_path: Path) -> None:
    existing = tmp_path / "old.mcap"
    existing.write_bytes(b"keep me")
    code = mcsm_main(["serve", "--listen", f"tcp/127.0.0.1:{free_port()}", "--record",
                      str(existing), "--log-level", "ERROR"])
    assert code == 2 and existing.read_bytes() == b"keep me"


def test_info_reports_where_the_maps_edges_live(server: Daemon) -> None:
    """``info`` carries the map's device and the bytes it holds there (issue 25); a map on
    the CPU reports ``cpu``, the bytes of its edges, and no device memory free."""
    rng = np.random.default_rng(4409)
    with MapClient(map="a", connect=server.endpoint, timeout_s=5) as c:
        c.update("dev0", "dev1", noisy_at(rng, N, [1.0, 0.0, 0.0]))
        info = c.info()
    assert info.device == "cpu"
    assert info.device_bytes >= 2 * 7 * N * 8
    assert info.device_free_bytes == 0


def test_serve_on_cuda_without_a_gpu_is_one_clear_line(tmp_path: Path,
                                                       capsys: pytest.CaptureFixture[str]) -> None:
    try:
        import cupy

        if cupy.cuda.runtime.getDeviceCount() > 0:
            pytest.skip("a GPU is present")
    except Exception:  # no CuPy or no driver: the case under test
        pass
    code = mcsm_main(["serve", "--device", "cuda", "--listen", f"tcp/127.0.0.1:{free_port()}",
                      "--record", str(tmp_path / "r.mcap")])
    err = capsys.readouterr().err
    assert code == 2
    assert err.count("\n") == 1 and "device='cuda'" in err
