"""mcsm.serve: the daemon, above the recording (:mod:`mcsm.log`) and the map (:mod:`mcsm.map`).

``server`` the map server (one worker applying every map's operations in sequence order,
Zenoh queryables, the recorder); ``lanes`` the worker's byte-bounded request queue;
``host`` the narrow interface replication is given to the server; ``replication`` one map's
role on a replicated server (standby or primary) over ``replication_link`` (the NATS
connection), ``replication_log`` (the map's stream), ``replication_lease`` (the lease) and
``replication_defaults``; ``natsrun`` a NATS cluster on this machine; ``connect`` the Zenoh
connection options every command shares. Imports point down: connect, lanes, natsrun,
replication_defaults < replication_link, replication_lease < replication_log < host <
replication < server. This package imports nothing itself.
"""
