"""The map layer: what one served map is, above the codec and below the server.

:mod:`~mcsm.map.ops` (the one table of operations), :mod:`~mcsm.map.deferral` (the gate and
``--gate-defer``), :mod:`~mcsm.map.history` (the retract window), :mod:`~mcsm.map.idmemory`
(the request ids it remembers), :mod:`~mcsm.map.state` (a map's state: applies through the
table) and :mod:`~mcsm.map.carry` (that state in a snapshot). Imports point down only:
deferral and idmemory < ops < history < state < carry; the package imports :mod:`mcsm.wire`,
:mod:`mcsm.core` and :mod:`mcsm.errors`, never the server, replication or the recording.
"""
