"""The defaults of ``mcsm serve``'s replication flags (``--replicas``, ``--lease-ttl``,
``--log-max-bytes``, ``--log-max-age``), importable without nats-py: ``mcsm serve --help`` and a
server without ``--nats`` import this module, never :mod:`mcsm.serve.replication`'s NATS client."""

DEFAULT_REPLICAS = 3
"""Copies of each map's log, lease and snapshots (JetStream R; a quorum is 2 of 3)."""
DEFAULT_LEASE_TTL_S = 2.0
"""Seconds a map's lease lasts unless renewed (a SIGKILLed primary's standby waits this long)."""
DEFAULT_LOG_MAX_BYTES = 1 << 30
"""Bytes each map's log keeps (the oldest inputs dropped first; late standbys then start from
the latest snapshot)."""
DEFAULT_LOG_MAX_AGE_S = 0.0
"""Seconds each map's log keeps an input (0: no age limit)."""

__all__ = ["DEFAULT_LEASE_TTL_S", "DEFAULT_LOG_MAX_AGE_S", "DEFAULT_LOG_MAX_BYTES",
           "DEFAULT_REPLICAS"]
