"""The options of ``mcsm serve`` (:class:`ServerOptions`) and the two pieces of the server's
startup that need no Zenoh session: making a new map from its options (:func:`new_map`) and
the one-line summary of a ``--restore`` (:func:`restore_summary`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from mcsm import wire
from mcsm.core.smap import StochasticMap
from mcsm.map.deferral import DeferOptions
from mcsm.map.history import DEFAULT_SNAPSHOT_EVERY, DEFAULT_SNAPSHOTS_KEPT, DEFAULT_WINDOW_BYTES
from mcsm.map.state import DEFAULT_ID_TTL_S, DEFAULT_LRU

if TYPE_CHECKING:  # only a server with --nats imports NATS (mcsm.serve.replication_link)
    from mcsm.serve.replication_link import NatsOptions


@dataclass
class ServerOptions:
    """Everything ``mcsm serve`` configures (see :func:`mcsm.cli.main`)."""

    maps: list[str] = field(default_factory=lambda: [wire.DEFAULT_MAP])
    prefix: str = wire.DEFAULT_PREFIX
    map_options: dict[str, Any] = field(default_factory=lambda: {"n_samples": 1000})
    """Constructor arguments of new maps (:func:`new_map`; the gate defaults to 0.99)."""
    record: Path | None = None
    restore: Path | list[Path] | None = None
    """A recording, or the files of a split recording in set order
    (:func:`mcsm.log.recset.resolve`)."""
    checkpoint_every: int = 100
    queue_size: int = 1024
    queue_bytes: int = 128 * 1024 * 1024
    """Payload bytes the write lane (and the read lane) holds at most before ``Busy``."""
    retract_window_bytes: int = DEFAULT_WINDOW_BYTES
    """Bytes each map's retract window holds at most (:mod:`mcsm.history`)."""
    split_bytes: int = 0
    """Start a new recording file once the current one holds this many bytes (0: never)."""
    split_s: float = 0.0
    """Start a new recording file once the current one is this many seconds old (0: never)."""
    lru_size: int = DEFAULT_LRU
    id_ttl_s: float = DEFAULT_ID_TTL_S
    fsync: bool = False
    snapshot_every: int = DEFAULT_SNAPSHOT_EVERY
    snapshots_kept: int = DEFAULT_SNAPSHOTS_KEPT
    disk_snapshot_every: int = 1000
    """Record the whole state every K operations of a map (0: never); --restore starts from
    the latest."""
    gate_defer: DeferOptions | None = None
    """``--gate-defer``: hold the first closure of a revisit until a second one agrees (None:
    off). Recorded in the map's config; a restored map keeps its recorded policy."""
    standby_of: list[str] = field(default_factory=list)
    """Maps this server follows as a hot standby (:mod:`mcsm.serve.replication`; needs ``nats``)."""
    nats: NatsOptions | None = None
    """``--nats``: replicate every map through this NATS JetStream cluster."""
    device: str = "cpu"
    """``--device``: where this server's maps keep their edges (``cpu`` or ``cuda``; not a
    map option: digests are the same on every device). A standby's map, and one rebuilt
    after a demotion (:mod:`mcsm.serve.replication`), stays on the CPU."""


def restore_summary(rep: Any) -> str:
    """How each map of a ``--restore`` was rebuilt: ``map 'default': snapshot at seq 1000 +
    332 inputs`` (the recording's state snapshot it started from, and the inputs applied after
    it), or ``map 'm': 12 inputs`` when it had none."""
    start: dict[str, int] = {}
    for cp in rep.checkpoints:  # the first snapshot of each map is the one replay started from
        if cp.reason == "snapshot":
            start.setdefault(cp.map, cp.seq)
    parts = []
    for name, st in rep.states.items():
        s0 = start.get(name)
        if s0 is not None and rep.snapshots_loaded:
            parts.append(f"map {name!r}: snapshot at seq {s0} + {st.seq - s0} inputs")
        else:
            parts.append(f"map {name!r}: {st.seq} inputs")
    return "; ".join(parts) or "no map"


def new_map(map_options: dict[str, Any], device: str = "cpu") -> StochasticMap:
    """A new map from the constructor arguments ``map_options`` (``n_samples`` and keywords):
    what is not given takes the constructor's default (the gate's: 0.99). Recorded options go
    through :meth:`StochasticMap.from_options` instead, where a missing gate means none."""
    o = dict(map_options)
    return StochasticMap(int(o.pop("n_samples")), **o, device=device)
