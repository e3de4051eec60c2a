"""Fixtures of the service tests (helpers live in daemon_util.py)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from mcsm.serve.natsrun import NatsCluster

from tests.service.daemon_util import Daemon


@pytest.fixture
def daemons(tmp_path: Path) -> Iterator[list[Daemon]]:
    """A list to put started daemons in; any still running at teardown is killed."""
    started: list[Daemon] = []
    yield started
    for d in started:
        if d.proc.poll() is None:
            d.proc.kill()
            d.proc.wait(timeout=10)



@pytest.fixture
def nats(tmp_path: Path) -> Iterator[NatsCluster]:
    """A three-node NATS JetStream cluster on loopback (the fleet's log), stopped after."""
    c = NatsCluster(tmp_path / "nats").start()
    try:
        yield c
    finally:
        c.stop()
