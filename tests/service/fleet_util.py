"""Helpers of the replicated-fleet tests: a NATS JetStream cluster, a TCP proxy that can cut a
link (reset every connection, or go silent), streaming client processes and the checks on
their acknowledgements and the servers' recordings.

Every process is real and on 127.0.0.1; every wait is bounded.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import threading
from dataclasses import dataclass
from pathlib import Path

from mcsm.log.reader import RecordingReader
from mcsm.log.replay import replay
from mcsm.log.topics import TOPIC_CHECKPOINT, TOPIC_CONFIG, TOPIC_OPS
from mcsm.serve.natsrun import NatsCluster

from tests.service.daemon_util import Daemon, start_daemon

REPO = Path(__file__).resolve().parents[2]
N = 32

__all__ = ["LEASE_TTL_S", "Ack", "NatsCluster", "StreamClient", "TcpProxy", "Term", "check_acks",
           "inputs", "replicated_server", "terms"]


class TcpProxy:
    """Forwards TCP connections from a free loopback port to ``target`` (``host:port``).

    :meth:`cut` with ``"reset"`` closes every connection with a reset and refuses new ones
    (reset at once); with ``"silent"`` it stops moving bytes (connections stay open, new ones
    are accepted and held), as a link that drops every packet. :meth:`heal` lets bytes flow
    again (held and new connections go through; reset ones are gone).
    """

    def __init__(self, target: str) -> None:
        host, port = target.rsplit(":", 1)
        self.target = (host, int(port))
        self._srv = socket.socket()
        self._srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._srv.bind(("127.0.0.1", 0))
        self._srv.listen(64)
        self._srv.settimeout(0.2)
        self.port = int(self._srv.getsockname()[1])
        self.mode = "open"
        self._flowing = threading.Event()
        self._flowing.set()
        self._lock = threading.Lock()
        self._conns: list[socket.socket] = []
        self._closed = False
        threading.Thread(target=self._accept, daemon=True, name="proxy-accept").start()

    @property
    def endpoint(self) -> str:
        return f"127.0.0.1:{self.port}"

    def _accept(self) -> None:
        while not self._closed:
            try:
                c, _ = self._srv.accept()
            except (TimeoutError, OSError):
                continue
            if self.mode == "reset":
                _reset(c)
                continue
            threading.Thread(target=self._open, args=(c,), daemon=True).start()

    def _open(self, c: socket.socket) -> None:
        self._flowing.wait(120.0)  # a silent link holds a new connection until it heals
        if self.mode == "reset" or self._closed:
            _reset(c)
            return
        try:
            up = socket.create_connection(self.target, timeout=5.0)
        except OSError:
            _reset(c)
            return
        with self._lock:
            self._conns += [c, up]
        for a, b in ((c, up), (up, c)):
            threading.Thread(target=self._pump, args=(a, b), daemon=True).start()

    def _pump(self, src: socket.socket, dst: socket.socket) -> None:
        src.settimeout(0.2)
        while not self._closed:
            try:
                data = src.recv(65536)
            except TimeoutError:
                continue
            except OSError:
                break
            if not data:
                break
            while not self._flowing.wait(0.2):  # silent: hold the bytes
                if self._closed or self.mode == "reset":
                    return
            try:
                dst.sendall(data)
            except OSError:
                break
        for s in (src, dst):
            try:
                s.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass

    def cut(self, mode: str) -> None:
        assert mode in ("reset", "silent")
        self.mode = mode
        self._flowing.clear()
        if mode == "reset":
            with self._lock:
                conns, self._conns = self._conns, []
            for s in conns:
                _reset(s)

    def heal(self) -> None:
        self.mode = "open"
        self._flowing.set()

    def close(self) -> None:
        self._closed = True
        self._flowing.set()
        self._srv.close()
        with self._lock:
            for s in self._conns:
                _reset(s)


def _reset(s: socket.socket) -> None:
    try:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, b"\x01\x00\x00\x00\x00\x00\x00\x00")
        s.close()
    except OSError:
        pass


LEASE_TTL_S = float(os.environ.get("MCSM_TEST_LEASE_TTL", "2"))
"""The servers' ``--lease-ttl`` (mcsm serve's default, 2 s; ``MCSM_TEST_LEASE_TTL`` changes it
for a measurement: docs/fleet.md, "Choosing --lease-ttl")."""


def replicated_server(tmp: Path, name: str, zenoh: str, nats: list[str], *args: str,
                      role: str = "standby") -> Daemon:
    """``mcsm serve`` of map ``m`` joined to router ``zenoh`` and the NATS nodes ``nats``:
    the primary (``role="primary"``: ``--map m``) or a standby (``--standby-of m``)."""
    which = ["--map", "m"] if role == "primary" else ["--standby-of", "m"]
    return start_daemon(tmp, "--samples", str(N), *which, "--connect", zenoh, "--nats",
                        ",".join(nats), "--lease-ttl", f"{LEASE_TTL_S:g}", *args, name=name,
                        endpoint="-")


@dataclass(frozen=True)
class Ack:
    rid: str
    seq: int
    server: str
    t: float
    duplicate: bool
    sent: float
    """When the client first sent the update: the server acknowledged it after that."""


class StreamClient:
    """``python -m tests.service.stream_client``: one client process streaming acknowledged
    updates on its own chain until :meth:`stop`."""

    def __init__(self, tmp: Path, endpoint: str, no: int, timeout_s: float = 60.0) -> None:
        self.acks_path = tmp / f"acks{no}.txt"
        self.stop_path = tmp / f"stop{no}"
        self.log = tmp / f"client{no}.log"
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "tests.service.stream_client", endpoint, "m", str(no),
             str(N), str(self.acks_path), str(self.stop_path), str(timeout_s)], cwd=REPO,
            stderr=open(self.log, "w"),  # noqa: SIM115
            env=dict(os.environ, PYTHONUNBUFFERED="1"))

    def acks(self) -> list[Ack]:
        if not self.acks_path.exists():
            return []
        out = []
        for line in self.acks_path.read_text().splitlines():
            rid, seq, server, t, dup, sent = line.split()
            out.append(Ack(rid, int(seq), server, float(t), dup == "1", float(sent)))
        return out

    def stop(self, timeout_s: float = 120.0) -> int:
        self.stop_path.touch()
        try:
            return self.proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(timeout=30)
            raise AssertionError(f"client did not stop: {self.log.read_text()[-2000:]}"
                                 ) from None


def inputs(path: Path) -> dict[int, str]:
    """seq -> request id of every input of map ``m`` in a recording (cut files too); fails on
    a seq recorded twice."""
    out: dict[int, str] = {}
    for item in RecordingReader(path):
        if item.topic in TOPIC_OPS and item.data.get("map") == "m":
            seq = int(item.data["seq"])
            assert seq not in out, f"{path.name}: seq {seq} recorded twice"
            out[seq] = str(item.data["id"])
    return out


@dataclass(frozen=True)
class Term:
    """A server's time as the map's primary, from its recording: from ``seq`` (the map's seq
    when it took over) and wall time ``t`` (its ``takeover`` checkpoint, written after it held
    the lease and before it acknowledged anything)."""

    server: str
    seq: int
    t: float


def terms(records: list[Path], first_primary: str) -> list[Term]:
    """Every primary term of map ``m`` in time order: ``first_primary`` (a server id) from
    seq 0, then each recording's ``takeover`` checkpoints."""
    out = [Term(first_primary, 0, float("-inf"))]
    for p in records:
        sid = ""
        for item in RecordingReader(p):
            if item.topic == TOPIC_CONFIG:
                sid = str(item.data.get("server_id", ""))
            elif item.topic == TOPIC_CHECKPOINT and item.data.get("reason") == "takeover" \
                    and item.data.get("map") == "m":
                out.append(Term(sid, int(item.data["seq"]), item.log_time_ns / 1e9))
    return sorted(out, key=lambda x: x.t)


def check_acks(acks: list[Ack], final_record: Path, final_digest: str,
               records: list[Path], first_primary: str) -> dict[str, int]:
    """The promises under faults, from the clients' acks and the servers' recordings:

    * every acknowledged request id is in the final map's recording under its acked seq
      (0 lost), and no id is recorded twice (0 applied twice); the recording's seqs are
      1..head and it replays to ``final_digest``;
    * at most one server acknowledged at any time: no two servers acked the same seq; the
      primary terms (:func:`terms`) follow each other in seq order; each fresh ack of seq
      ``s`` comes from the server whose term holds ``s`` (the last takeover below ``s``), and
      that server had the request (the client sent it, the server received it: its
      ``recv_ns`` in the log) before the next term's takeover, so it acknowledged it before
      another server could;
    * every other recording replays identical and agrees with the final one on every seq
      both hold.

    Returns request id -> seq of the acknowledged updates.
    """
    by_rid: dict[str, int] = {}
    for a in acks:
        assert by_rid.setdefault(a.rid, a.seq) == a.seq, f"{a.rid} acked as two seqs"
    recorded = inputs(final_record)
    assert sorted(recorded) == list(range(1, len(recorded) + 1)), "recorded seqs not dense"
    ids = {rid: seq for seq, rid in recorded.items()}
    assert len(ids) == len(recorded), "an input was applied twice"
    lost = {r: s for r, s in by_rid.items() if ids.get(r) != s}
    assert not lost, f"acknowledged updates lost or moved: {sorted(lost.items())[:5]}"
    rep = replay(final_record)
    assert rep.divergence is None and rep.final_digests()["m"] == final_digest
    received = {int(it.data["seq"]): it.data["recv_ns"] / 1e9
                for it in RecordingReader(final_record)
                if it.topic in TOPIC_OPS and it.data.get("map") == "m"}
    by_seq: dict[int, str] = {}
    for a in acks:
        if not a.duplicate:
            assert by_seq.setdefault(a.seq, a.server) == a.server, \
                f"seq {a.seq} acked by two servers"
    ts = terms(records, first_primary)
    assert [x.seq for x in ts] == sorted(x.seq for x in ts), f"terms out of seq order: {ts}"
    for a in acks:
        if a.duplicate:
            continue
        k = max(i for i, x in enumerate(ts) if x.seq < a.seq)
        assert ts[k].server == a.server, \
            f"seq {a.seq} acked by {a.server} in {ts[k].server}'s term: {ts}"
        if k + 1 < len(ts):
            start = max(a.sent, received[a.seq])
            assert start < ts[k + 1].t, \
                f"seq {a.seq} acked by {a.server} after {ts[k + 1].server} took over: " \
                f"request at {start:.3f}, takeover at {ts[k + 1].t:.3f}"
    for p in records:
        r = replay(p)
        assert r.divergence is None, f"{p.name}: {r.divergence}"
        mine = inputs(p)
        assert all(recorded.get(s) == rid for s, rid in mine.items()), \
            f"{p.name} disagrees with the final recording"
    return by_rid
