"""Fixtures of the ROS 2 tests: a map server, the §6 simulation as ROS messages, the reference
map (the same constraints streamed through MapClient), and an environment that keeps ROS 2
(Fast DDS) on this host in a domain of this test run's own."""

from __future__ import annotations

import os
import random
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest
from mcsm.viz.rosmsg import rosbags_maker
from mcsm_client.client import MapClient
from mcsm_client.process import ServerProcess
from mcsm_client.ros2.bag import ApplyStats, send
from mcsm_client.ros2.mapping import MessageMapper, order_key
from mcsm_client.ros2.sim import SimMessage, build, sim_messages
from mcsm_client.scenario import PaperScenarioConfig, generate_paper_scenario
from rosbags.typesys import Stores, get_typestore

#: N of the ROS tests' maps; the short §6 run they stream
N = 64
ITERATIONS = 25
LANDMARKS = 40
MAPS = ("ref", "live", "mcap", "sqlite", "round", "shuffled", "gated")


@dataclass
class Reference:
    messages: list[SimMessage]
    decoded: list[Any]  # rosbags messages, same order
    seq: int
    digest: str
    stats: ApplyStats
    ids: list[str]  # request ids of the constraints, in order


@pytest.fixture(scope="session")
def ros_env() -> dict[str, str]:
    """Fast DDS on this host only (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, no static peers),
    in a ROS domain drawn for this run (so parallel runs do not meet)."""
    rng = random.Random(os.getpid() ^ int.from_bytes(os.urandom(4), "little"))
    # under pytest-xdist (gw0, gw1, ...) each worker takes its own residue, so the workers of one
    # run never share a domain
    worker = int(os.environ.get("PYTEST_XDIST_WORKER", "gw0")[2:] or 0)
    workers = max(1, int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")))
    domain = 1 + rng.randrange(100 // workers) * workers + worker % workers
    return {"ROS_DOMAIN_ID": str(domain), "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
            "ROS_STATIC_PEERS": "", "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp"}


@pytest.fixture(scope="session")
def ros_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServerProcess]:
    d = tmp_path_factory.mktemp("ros2srv")
    with ServerProcess(d / "ros.mcap", n_samples=N, maps=MAPS) as srv:
        yield srv
    assert srv.returncode == 0, srv.log_tail()


@pytest.fixture(scope="session")
def reference(ros_server: ServerProcess) -> Reference:
    """The simulation's messages streamed through MapClient (map ``ref``), in order_key order
    with the node's mapping: what the node and the bag player must reproduce."""
    scen = generate_paper_scenario(PaperScenarioConfig(n_iterations=ITERATIONS,
                                                       n_landmarks=LANDMARKS),
                                   np.random.default_rng(11))
    messages = sim_messages(scen)
    make = rosbags_maker(get_typestore(Stores.ROS2_KILTED))
    decoded = [build(make, m) for m in messages]
    order = sorted(range(len(messages)), key=lambda i: order_key(
        messages[i].topic, "constraint" if "constraints" in messages[i].topic else "landmark",
        decoded[i], i))
    assert order == list(range(len(messages)))  # published in the order they are applied
    mapper = MessageMapper()
    stats = ApplyStats()
    ids = []
    with MapClient(map="ref", connect=ros_server.endpoint, timeout_s=10.0) as c:
        for m, msg in zip(messages, decoded, strict=True):
            for con in mapper.map(m.topic, msg, N):
                ids.append(con.request_id)
                send(c, con, stats)
        info = c.info()
    assert stats.n_refused == 0 and stats.invalid == 0, stats.summary()
    return Reference(messages, decoded, info.seq, info.digest, stats, ids)
