"""ROS 2 bags into a map (``mcsm-client play-rosbag``), and sending constraints with a tally.

:func:`read_bag` reads a ROS 2 bag (MCAP or sqlite3 storage, any bag rosbags reads) with
``rosbags``, no ROS installation needed, keeps the messages of the input topics of
:class:`mcsm_client.ros2.mapping.MappingOptions` and returns them in the order the node applies
them (:func:`mcsm_client.ros2.mapping.order_key`; ties keep the recorded order).
:func:`play_rosbag` maps them with the node's :class:`~mcsm_client.ros2.mapping.MessageMapper`
and sends each constraint with :func:`send` (request id from the message: a bag played twice
is applied once). :class:`ApplyStats` is the tally both the node and the player keep.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcsm.errors import McsmError, NoPermittedServer, NoServer, Timeout

from mcsm_client.ros2.mapping import (
    INPUT_TYPE,
    Constraint,
    MappingError,
    MappingOptions,
    MessageMapper,
    order_key,
)

__all__ = ["ApplyStats", "BagError", "BagMessage", "play_rosbag", "read_bag", "send"]


class BagError(Exception):
    """The bag cannot be read, or an input topic carries another message type."""


def _bump(d: dict[str, int], key: str) -> None:
    d[key] = d.get(key, 0) + 1


@dataclass
class ApplyStats:
    """What happened to the messages: sent and applied, duplicates, the gate's rejections,
    the server's refusals (per error type), invalid messages, odometry that made no
    keyframe."""

    received: int = 0
    applied: dict[str, int] = field(default_factory=dict)
    results: dict[str, int] = field(default_factory=dict)
    duplicates: int = 0
    rejected: int = 0
    refused: dict[str, int] = field(default_factory=dict)
    invalid: int = 0
    not_keyframes: int = 0
    first_error: str = ""
    last_verdict: str = ""
    last_request_id: str = ""
    elapsed_s: float = 0.0

    @property
    def n_applied(self) -> int:
        return sum(self.applied.values())

    @property
    def n_refused(self) -> int:
        return sum(self.refused.values())

    def invalid_message(self, where: str, exc: Exception) -> None:
        self.invalid += 1
        self.first_error = self.first_error or f"{where}: {exc}"

    def as_dict(self) -> dict[str, Any]:
        return {"received": self.received, "applied": dict(self.applied),
                "results": dict(self.results), "duplicates": self.duplicates,
                "rejected": self.rejected, "refused": dict(self.refused),
                "invalid": self.invalid, "not_keyframes": self.not_keyframes,
                "first_error": self.first_error, "elapsed_s": self.elapsed_s}

    def summary(self) -> str:
        """One line for people."""
        parts = [f"{self.received} messages, {self.n_applied} constraints applied"]
        if self.applied:
            parts.append(", ".join(f"{k} {v}" for k, v in sorted(self.applied.items())))
        if self.results:
            parts.append("map: " + ", ".join(f"{k} {v}" for k, v in sorted(self.results.items())))
        if self.duplicates:
            parts.append(f"{self.duplicates} already applied (duplicates)")
        if self.not_keyframes:
            parts.append(f"{self.not_keyframes} odometry messages between keyframes")
        if self.rejected:
            parts.append(f"{self.rejected} rejected by the gate")
        if self.refused:
            parts.append("refused: " + ", ".join(f"{k} {v}" for k, v in self.refused.items()))
        if self.invalid:
            parts.append(f"{self.invalid} invalid messages")
        parts.append(f"{self.elapsed_s:.1f} s")
        return "; ".join(parts)


def send(client: Any, c: Constraint, stats: ApplyStats) -> Any:
    """Send one constraint with its request id; tally the outcome; the ack (None if refused).

    Raises
    ------
    NoServer, NoPermittedServer, Timeout
        No answer: the caller stops (sending again later is safe, same request id).
    """
    stats.last_request_id = c.request_id
    fn = client.update_point if c.is_point else client.update
    try:
        ack = fn(c.a, c.b, c.samples, request_id=c.request_id, stamp_ns=c.stamp_ns)
    except (NoServer, NoPermittedServer, Timeout):
        raise
    except McsmError as exc:
        _bump(stats.refused, type(exc).__name__)
        stats.first_error = stats.first_error or f"{c.request_id} ({c.a} -> {c.b}): {exc}"
        return None
    v = ack.verdict
    stats.last_verdict = v.status if v is not None else ack.kind
    if ack.duplicate:
        stats.duplicates += 1
    elif v is not None and v.status == "rejected":
        stats.rejected += 1
    else:
        _bump(stats.applied, c.kind)
        _bump(stats.results, str(ack.kind))
    return ack


@dataclass(frozen=True)
class BagMessage:
    """One input message of a bag: its topic, kind, order key and decoded message."""

    key: tuple[int, int, str, int]
    topic: str
    log_time_ns: int
    msg: Any


def read_bag(path: str | Path, options: MappingOptions) -> tuple[list[BagMessage], list[str]]:
    """The bag's input messages in the order they are applied, and the topics it skipped.

    Raises
    ------
    BagError
        Unreadable bag, or an input topic whose type is not ``nav_msgs/msg/Odometry``.
    """
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    p = Path(path)
    if not p.exists():
        raise BagError(f"no such bag: {p}")
    out: list[BagMessage] = []
    try:
        with AnyReader([p], default_typestore=get_typestore(Stores.ROS2_KILTED)) as reader:
            conns = []
            skipped = sorted({c.topic for c in reader.connections
                              if options.kind_of(c.topic) is None})
            for c in reader.connections:
                if options.kind_of(c.topic) is None:
                    continue
                if c.msgtype != INPUT_TYPE:
                    raise BagError(f"topic {c.topic} carries {c.msgtype}, not {INPUT_TYPE}")
                conns.append(c)
            if not conns:  # an empty list would make rosbags read every topic
                raise BagError(
                    f"{p} has none of the input topics ({', '.join(options.topics)}); its "
                    f"topics: {', '.join(skipped) or 'none'}. Name yours with --odometry-topic,"
                    " --constraint-topic or --landmark-topic")
            for i, (conn, t, raw) in enumerate(reader.messages(connections=conns)):
                msg = reader.deserialize(raw, conn.msgtype)
                kind = options.kind_of(conn.topic)
                assert kind is not None
                out.append(BagMessage(order_key(conn.topic, kind, msg, i), conn.topic, int(t),
                                      msg))
    except BagError:
        raise
    except Exception as exc:  # rosbags raises its own errors per storage and version
        raise BagError(f"cannot read {p} as a ROS 2 bag: {type(exc).__name__}: {exc}") from None
    out.sort(key=lambda m: m.key)
    return out, skipped


Progress = Callable[[int, int, ApplyStats], None]


def play_rosbag(path: str | Path, client: Any, options: MappingOptions | None = None, *,
                progress: Progress | None = None) -> ApplyStats:
    """Stream a bag's input messages into the map behind ``client`` (a ``MapClient``).

    Raises
    ------
    BagError
        As :func:`read_bag`.
    NoServer, NoPermittedServer, Timeout
        The server stopped answering (play the bag again: what was applied stays applied once).
    """
    opts = options or MappingOptions()
    t0 = time.perf_counter()
    messages, _ = read_bag(path, opts)
    n = int(client.info().n_samples)
    mapper = MessageMapper(opts)
    stats = ApplyStats()
    for done, m in enumerate(messages, start=1):
        stats.received += 1
        try:
            constraints = mapper.map(m.topic, m.msg, n)
        except (MappingError, ValueError, ArithmeticError) as exc:  # numpy's LinAlgError too
            stats.invalid_message(f"{m.topic} at {m.key[0]} ns", exc)
            constraints = []
        else:
            if not constraints:
                stats.not_keyframes += 1
        for c in constraints:
            send(client, c, stats)
        if progress is not None:
            progress(done, len(messages), stats)
    stats.elapsed_s = time.perf_counter() - t0
    return stats
