"""Network partitions of a replicated fleet (issue 23): two sides, A and B, each with its own
Zenoh router and its own NATS JetStream nodes; the link between them cut for 8 s, then
healed, while a client on each side streams acknowledged updates.

The cut is one of three kinds: ``bridge`` (the Zenoh bridge router killed and restarted; the
NATS routes between the sides reset), ``reset`` (every cross-side TCP link, Zenoh and NATS,
reset and refused) and ``silent`` (every cross-side link stops moving bytes, connections held
open). Topologies: the primary's side holds the NATS minority (1 of 3 nodes) or the majority;
its standby on the same side, on the other side, or standbys on both (K = R = 3 as shipped:
``--replicas 3``, quorum 2).

Each run checks (``fleet_util.check_acks``): 0 acknowledged updates lost from the final map
and its recordings, 0 applied twice, one acknowledging server at a time (from the acks'
server ids and seqs), every recording replaying identical; the map writable on both sides
within ``HEAL_BOUND_S`` of the heal; every server process still running (no restart).

The whole matrix is ``make test-fleet`` (marker ``fleet``); ``make test`` runs one
representative run (the primary cut off on the minority side, its standby across the cut).
"""

from __future__ import annotations

import json
import signal
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path

import pytest
from mcsm.serve.natsrun import NatsCluster
from mcsm_client.client import MapClient
from mcsm_client.process import McsmProcess

from tests.service.daemon_util import Daemon, start_router, wait_for
from tests.service.fleet_util import (
    LEASE_TTL_S,
    StreamClient,
    TcpProxy,
    check_acks,
    replicated_server,
)

CUT_S = 8.0
STANDBY_BOUND_S = 30.0
"""After the clients stop, every standby reports the head within this many seconds."""
HEAL_BOUND_S = 30.0
"""After the heal, each side's client gets a fresh ack within this many seconds. At the heal
the rejoining NATS node's higher raft term makes the leaders step down, and JetStream elects
again: 4-9 s a round (nats-server's own randomised timeouts, not configurable), and a round
can fail (a candidate whose log is behind, a split vote) and start another. The bound allows
two rounds (18 s), the lease's TTL (2 s), a takeover (catching up from the log), the
client's backoff (1 s) and load on a shared 2-core machine. Measured here: median 7.6 s, worst
12.8 s in 125 runs; one run in CI took over 20 s (the bound was 20 s then)."""


@dataclass
class Sides:
    """The two sides: routers, NATS nodes (``nats_a``/``nats_b``: indices), the links."""

    tmp: Path
    kind: str
    nats_a: list[int]
    nats_b: list[int]
    cluster: NatsCluster | None = None
    proxies: dict[tuple[int, int], TcpProxy] = field(default_factory=dict)
    ra: tuple[McsmProcess, str] | None = None
    rb: tuple[McsmProcess, str] | None = None
    zlink: TcpProxy | None = None
    bridge: McsmProcess | None = None
    bridge_conf: Path | None = None

    def side(self, i: int) -> str:
        return "a" if i in self.nats_a else "b"

    def start(self) -> None:
        # One proxy per (dialer, dialled) pair of NATS nodes, bound first so that the ports
        # the cluster then picks cannot be one of theirs; each is pointed at the dialled
        # node's cluster port once the cluster has picked it. The nodes start (and bind
        # their ports) before the routers pick theirs.
        self.proxies = {(i, j): TcpProxy("127.0.0.1:1") for i in range(3) for j in range(3)
                        if i != j}
        self.cluster = NatsCluster(self.tmp / "nats",
                                   route_via=lambda i, j: self.proxies[(i, j)].endpoint)
        for (_, j), proxy in self.proxies.items():
            proxy.target = ("127.0.0.1", self.cluster.nodes[j].cluster_port)
        self.cluster.start()
        self.ra = start_router(self.tmp)
        self._start_rb()

    def _start_rb(self) -> None:
        assert self.ra is not None
        if self.kind == "bridge":
            self.rb = start_router(self.tmp)
            self.bridge_conf = self.tmp / "bridge.json5"
            self.bridge_conf.write_text(json.dumps({
                "mode": "router", "connect": {"endpoints": [self.ra[1], self.rb[1]]},
                "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}}}))
            self._start_bridge()
        else:
            self.zlink = TcpProxy(self.ra[1].split("/", 1)[1])
            conf = self.tmp / "rb.json5"
            conf.write_text(json.dumps({
                "mode": "router", "connect": {"endpoints": [f"tcp/{self.zlink.endpoint}"]},
                "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}}}))
            self.rb = start_router(self.tmp, "--zenoh-config", str(conf))

    def _start_bridge(self) -> None:
        assert self.bridge_conf is not None
        self.bridge, _ = start_router(self.tmp, "--zenoh-config", str(self.bridge_conf))

    def urls(self, side: str) -> list[str]:
        assert self.cluster is not None
        return [self.cluster.nodes[i].url for i in (self.nats_a if side == "a" else self.nats_b)]

    def zenoh(self, side: str) -> str:
        assert self.ra is not None and self.rb is not None
        return self.ra[1] if side == "a" else self.rb[1]

    def cut(self) -> None:
        mode = "reset" if self.kind == "bridge" else self.kind
        for (i, j), p in self.proxies.items():
            if self.side(i) != self.side(j):
                p.cut(mode)
        if self.kind == "bridge":
            assert self.bridge is not None
            self.bridge.stop(signal.SIGKILL)
        else:
            assert self.zlink is not None
            self.zlink.cut(mode)

    def heal(self) -> None:
        for p in self.proxies.values():
            p.heal()
        if self.kind == "bridge":
            self._start_bridge()
        else:
            assert self.zlink is not None
            self.zlink.heal()

    def stop(self) -> None:
        for r in (self.ra, self.rb):
            if r is not None:
                r[0].stop(signal.SIGKILL)
        if self.bridge is not None:
            self.bridge.stop(signal.SIGKILL)
        if self.cluster is not None:
            self.cluster.stop()
        for p in [*self.proxies.values(), *([self.zlink] if self.zlink else [])]:
            p.close()


def _fresh_ack_after(client: StreamClient, t0: float) -> bool:
    return any(a.t > t0 and not a.duplicate for a in client.acks())


def run_partition(tmp: Path, kind: str, primary_side: str, standbys: str,
                  daemons: list[Daemon]) -> None:
    """One run: ``primary_side`` holds the NATS ``majority`` or ``minority``; ``standbys``:
    ``same`` (one on the primary's side), ``other`` (one on the other side) or ``both``."""
    nats_a, nats_b = ([0, 1], [2]) if primary_side == "majority" else ([0], [1, 2])
    sides = Sides(tmp, kind, nats_a, nats_b)
    clients: list[StreamClient] = []
    try:
        sides.start()
        where = {"same": ["a"], "other": ["b"], "both": ["a", "b"]}[standbys]
        servers: dict[str, Daemon] = {}
        with ThreadPoolExecutor(len(where)) as pool:  # standbys wait for the map's log
            later = {f"s{k}": pool.submit(replicated_server, tmp, f"s{k}", sides.zenoh(side),
                                          sides.urls(side)) for k, side in enumerate(where)}
            try:
                servers["p"] = replicated_server(tmp, "p", sides.zenoh("a"), sides.urls("a"),
                                                 role="primary")
            finally:  # every started server is stopped at teardown, whatever failed
                for name, f in later.items():
                    if f.exception() is None:
                        servers[name] = f.result()
                daemons += servers.values()
        for f in later.values():
            f.result()  # a standby that did not start fails the test with its reason
        with MapClient(map="m", connect=sides.zenoh("a"), timeout_s=30.0) as w:
            wait_for("the standbys consume", lambda: len(w.info().standbys) == len(where))
        clients = [StreamClient(tmp, sides.zenoh("a"), 0), StreamClient(tmp, sides.zenoh("b"), 1)]
        wait_for("both clients acknowledged", lambda: all(len(c.acks()) >= 5 for c in clients))
        t_cut = time.time()
        sides.cut()
        time.sleep(CUT_S)
        t_heal = time.time()
        sides.heal()
        for side, c in zip("ab", clients, strict=True):
            try:
                wait_for(f"a fresh ack on side {side} after the heal",
                         lambda c=c: _fresh_ack_after(c, t_heal), HEAL_BOUND_S)
            except AssertionError as exc:
                raise AssertionError(f"{exc}\n{_heal_report(tmp, clients, servers, t_heal)}"
                                     ) from None
        writable = [min(a.t for a in c.acks() if a.t > t_heal and not a.duplicate) - t_heal
                    for c in clients]
        (tmp / "partition.json").write_text(json.dumps({  # for benchmarks/partition_summary.py
            "kind": kind, "primary_side": primary_side, "standbys": standbys,
            "lease_ttl_s": LEASE_TTL_S, "t_cut": t_cut, "t_heal": t_heal,
            "heal_to_fresh_ack_s": writable}))
        time.sleep(1.0)
        for c in clients:
            assert c.stop() == 0, c.log.read_text()[-3000:]
        for name, d in servers.items():
            assert d.proc.poll() is None, f"{name} exited: {d.log_text()[-2000:]}"
        with MapClient(map="m", connect=sides.zenoh("a"), timeout_s=30.0) as w:
            final = w.info()
            seen: list[dict[str, int]] = []

            def caught_up() -> bool:
                seen.append(w.info().standbys)
                return len(seen[-1]) == len(where) and min(seen[-1].values()) >= final.seq

            try:
                wait_for(f"every standby at seq {final.seq}", caught_up, STANDBY_BOUND_S)
            except AssertionError as exc:
                raise AssertionError(f"{exc}; info.standbys last: {seen[-1:]}") from None
        primary = next(n for n, d in servers.items() if _server_id(d) == final.server_id)
        for name in [n for n in servers if n != primary]:
            assert servers[name].stop() == 0
        assert servers[primary].stop() == 0
    finally:
        for c in clients:
            if c.proc.poll() is None:
                c.proc.kill()
        sides.stop()
    acks = [a for c in clients for a in c.acks()]
    got = check_acks(acks, servers[primary].record, final.digest,
                     [d.record for d in servers.values()], _server_id(servers["p"]))
    assert len(got) >= 10


_NATS_EVENTS = ("leader", "stepdown", "no metadata leader")


def _heal_report(tmp: Path, clients: list[StreamClient], servers: dict[str, Daemon],
                 t_heal: float) -> str:
    """What a run that did not heal in time was doing, for its failure message: each side's
    last ack, every server's log after the cut (DEBUG lines left out) and the NATS nodes'
    leader elections, times relative to the heal."""
    def rel(stamp: str, fmt: str) -> str:
        try:
            t = datetime.strptime(stamp, fmt).timestamp()
        except ValueError:
            return stamp
        return f"{t - t_heal:+7.2f} s"

    out = []
    for side, c in zip("ab", clients, strict=True):
        acks = c.acks()
        last = f"{acks[-1].t - t_heal:+.2f} s ({acks[-1].rid})" if acks else "none"
        out.append(f"side {side}: {len(acks)} acks, the last at {last}; its client's log:")
        lines = c.log.read_text(errors="replace").splitlines()
        out += [f"{rel(ln[:23], '%Y-%m-%d %H:%M:%S,%f')} {ln[24:200]}" for ln in lines[-8:]]
    for name, d in servers.items():
        lines = [ln for ln in d.log_text().splitlines() if " DEBUG " not in ln]
        out.append(f"--- server {name}, last lines:")
        out += [f"{rel(ln[:23], '%Y-%m-%d %H:%M:%S,%f')} {ln[24:200]}" for ln in lines[-25:]]
    for log in sorted((tmp / "nats").glob("*.log")):
        ev = [ln for ln in log.read_text(errors="replace").splitlines()
              if any(k in ln for k in _NATS_EVENTS)]
        out.append(f"--- {log.name}, leader events:")
        out += [f"{rel(' '.join(ln.split()[1:3]), '%Y/%m/%d %H:%M:%S.%f')} "
                f"{' '.join(ln.split()[3:])[:160]}" for ln in ev[-12:]]
    return "\n".join(out)


def _server_id(d: Daemon) -> str:
    from mcsm.log.reader import RecordingReader
    from mcsm.log.topics import TOPIC_CONFIG

    for item in RecordingReader(d.record):
        if item.topic == TOPIC_CONFIG:
            return str(item.data.get("server_id", ""))
    return ""


MATRIX = [(kind, side, sb) for kind in ("bridge", "reset", "silent")
          for side in ("minority", "majority") for sb in ("same", "other", "both")]
IN_MAKE_TEST = {("reset", "minority", "other")}


@pytest.mark.parametrize(("kind", "primary_side", "standbys"), [
    pytest.param(*m, marks=[] if m in IN_MAKE_TEST else [pytest.mark.fleet]) for m in MATRIX])
def test_partition(tmp_path: Path, daemons: list[Daemon], kind: str, primary_side: str,
                   standbys: str) -> None:
    run_partition(tmp_path, kind, primary_side, standbys, daemons)
