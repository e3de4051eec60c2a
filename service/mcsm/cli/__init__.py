"""``mcsm``: run the map server, replay, inspect, recover and print its recordings.

::

    mcsm serve [--listen tcp/127.0.0.1:7457] [--map NAME]... [--samples N]
               [--method joint|paper] [--gate Q|none] [--gate-defer [K]]
               [--gate-scale W:T:S|none] [--history BYTES|none] [--relinearize-nis Q|none]
               [--relinearize-every K|none] [--relinearize-gap K] [--relinearize-regate K|none]
               [--relinearize-spread S] [--[no-]relinearize-recentre]
               [--relinearize-readmit K|none] [--relinearize-calibrate K|none]
               [--record PATH.mcap] [--restore PATH.mcap] [--zenoh-config FILE]
               [--connect ENDPOINT]... [--nats URL]... [--standby-of MAP]...
    mcsm router --listen ENDPOINT
    mcsm nats-cluster --dir DIR [--port 4222] [--nodes 3] [--auth FILE]
    mcsm replay FILE.mcap... [--json]
    mcsm inspect FILE.mcap... [--json]
    mcsm recover IN.mcap... -o OUT.mcap|OUT_DIR
    mcsm cat FILE.mcap... [--json] [--samples]
    mcsm plot FILE.mcap -o map.png [--map NAME] [--at SEQ] [--samples] [--truth CSV]
              [--view auto|top|xz|yz|3d]
    mcsm export foxglove|g2o|tum FILE.mcap [-o OUT] [--map NAME] [--force] (export-foxglove:
                                  the same as export foxglove)
    mcsm view [--connect ENDPOINT] [--map NAME] [--foxglove-port P]   (mcsm_client's, through
                                  the entry-point group mcsm.commands)
    mcsm export-rosbag FILE.mcap -o BAG [--map NAME] [--at SEQ]          (ros extra)
    mcsm ros2 [--connect ENDPOINT | --serve] [--ros-args ...]            (ros extra)
    mcsm --version

``serve`` prints one line ``listening on <endpoint>`` on stdout when it is ready, and closes
the recording cleanly on SIGINT or SIGTERM. Exit codes: see :data:`EXIT_CODES_HELP` (also in
``mcsm --help`` and docs/recordings.md).

A split recording (``serve --split-size`` / ``--split-duration``) is read by naming its files:
several paths, a directory or a glob pattern (:mod:`mcsm.log.recset`); a gap or a mixed set is a
usage error (2).

The command lives in modules by concern: ``parser`` (the parser and :func:`main`), ``common``
(exit codes, file helpers), ``serve_cmd`` (``serve``, ``router``) and ``log_cmds``
(``replay``, ``inspect``, ``recover``, ``cat``); this module re-exports what scripts use.
"""

from mcsm.cli.common import (
    EXIT_CODES_HELP,
    EXIT_CUT,
    EXIT_DAMAGED,
    EXIT_DIVERGED,
    EXIT_OK,
    EXIT_OTHER_ARITHMETIC,
    EXIT_RECORDING_FAILED,
    EXIT_USAGE,
)
from mcsm.cli.parser import PLUGIN_GROUP, add_plugin_commands, build_parser, main

__all__ = ["EXIT_CODES_HELP", "EXIT_CUT", "EXIT_DAMAGED", "EXIT_DIVERGED", "EXIT_OK",
           "EXIT_OTHER_ARITHMETIC", "EXIT_RECORDING_FAILED", "EXIT_USAGE", "PLUGIN_GROUP",
           "add_plugin_commands", "build_parser", "main"]
