"""The narrow interface replication is given to its server: :class:`ReplicaHost`.

A :class:`~mcsm.serve.replication.Replica` never imports the server. The server hands each
replica itself as a ``ReplicaHost``: the few options a replica reads, the server's id, its
recorder and map states, the flag that stops it on a fatal error, and the three calls a
replica makes (run something on the worker between two operations, promote, demote). A test
or another daemon can host replicas by providing these and nothing else.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any, Protocol

from mcsm.log.writer import Recorder
from mcsm.map.state import MapState


class HostOptions(Protocol):
    """The server options a replica reads."""

    @property
    def checkpoint_every(self) -> int: ...
    @property
    def disk_snapshot_every(self) -> int: ...
    @property
    def id_ttl_s(self) -> float: ...
    @property
    def lru_size(self) -> int: ...


class ReplicaHost(Protocol):
    """What a replica may use of the server that hosts it."""

    @property
    def opts(self) -> HostOptions: ...
    @property
    def server_id(self) -> str: ...
    @property
    def recorder(self) -> Recorder | None: ...
    @property
    def states(self) -> dict[str, MapState]: ...
    @property
    def failed(self) -> threading.Event: ...

    def run_in_worker(self, run: Callable[[], Any], timeout_s: float) -> Any:
        """Run ``run`` on the worker, between two operations, and return its result."""
        ...

    # ``r`` is the calling Replica (typed Any here: the host interface sits below replication)
    def promote(self, r: Any) -> bool:
        """On the worker: serve ``r``'s map and acknowledge from now on (it holds the lease
        and applied the whole log); False if it cannot."""
        ...

    def demote(self, r: Any, why: str) -> None:
        """On the worker: stop serving ``r``'s map; it follows the log again."""
        ...
