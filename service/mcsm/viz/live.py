"""``mcsm view``: follow a live map over Zenoh and serve it to the Foxglove app.

A separate process (the server stays headless): a ``MapClient`` subscribes to
``<prefix>/<map>/events``; after each change (at most every ``min_interval_s``, and every
``poll_s`` in case an event was missed, since events are best effort) it asks ``info`` for the
components, fetches each one with the submap export RPC, rebuilds a local copy of the map with
``StochasticMap.import_component`` and publishes the scene of :mod:`mcsm.viz.foxglove_scene`
through foxglove-sdk's WebSocket server. The last scene is published again every
``republish_s`` so that a Foxglove app connecting later sees the map at once.

Reads only: the view never writes to the map.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from mcsm.errors import McsmError
from mcsm.viz.foxglove_scene import (
    DEFAULT_SAMPLES_PER_FRAME,
    SceneChannels,
    SceneSnapshot,
    build_snapshot,
    load_foxglove,
)
from mcsm.viz.scene import MapView, map_view

log = logging.getLogger("mcsm.view")


@dataclass
class ViewOptions:
    map: str = "default"
    connect: str | None = None
    zenoh_config: Any = None
    prefix: str = "mcsm"
    host: str = "127.0.0.1"
    foxglove_port: int = 8765
    samples_per_frame: int = DEFAULT_SAMPLES_PER_FRAME
    timeout_s: float = 10.0
    min_interval_s: float = 0.2
    poll_s: float = 2.0
    republish_s: float = 1.0


def fetch_view(client: Any, samples: bool) -> MapView:
    """The map behind ``client`` now, rebuilt locally from one export per component.

    Raises
    ------
    McsmError
        A call failed (``Timeout``, ...), or the map changed between the calls so that two
        exports overlap (``FrameExists``): the caller fetches again.
    """
    from mcsm.core import StochasticMap

    info = client.info()
    local = StochasticMap.from_options(dict(info.options))
    for root in info.components:
        local.import_component(client.export_submap(root))
    return map_view(local, map_name=info.map, seq=info.seq, samples=samples)


def run_view(opts: ViewOptions, stop: threading.Event,
             ready: Callable[[str], None] | None = None) -> int:
    """Serve the live scene until ``stop`` is set; returns 0.

    ``ready`` is called once with the WebSocket URL when the Foxglove server listens.

    Raises
    ------
    McsmError
        No server answers within ``opts.timeout_s``, or the WebSocket port cannot be opened.
    """
    from mcsm_client.client import MapClient

    fg = load_foxglove()
    where = opts.connect or "the configured endpoints"
    try:
        client = MapClient(map=opts.map, connect=opts.connect, zenoh_config=opts.zenoh_config,
                           timeout_s=opts.timeout_s, retries=0, prefix=opts.prefix)
    except McsmError:
        raise McsmError(f"cannot reach a Zenoh peer at {where} within {opts.timeout_s:g} s"
                        ) from None
    try:
        try:
            info = client.wait_for_server(timeout_s=opts.timeout_s)
        except McsmError:
            raise McsmError(f"no server answers for map {opts.map!r} at {where} within "
                            f"{opts.timeout_s:g} s") from None
        log.info("following map %r (seq %d, %d frames) of server %s", info.map, info.seq,
                 info.n_frames, info.server_id)
        ctx = fg.Context()
        try:
            server = fg.start_server(name=f"mcsm view {opts.map}", host=opts.host,
                                     port=opts.foxglove_port, context=ctx)
        except Exception as exc:  # foxglove raises its own error types for bind failures
            raise McsmError(f"cannot start the Foxglove WebSocket server on "
                            f"{opts.host}:{opts.foxglove_port}: {exc}") from None
        try:
            return _follow(client, server, ctx, opts, stop, ready)
        finally:
            server.stop()
    finally:
        client.close()


def _follow(client: Any, server: Any, ctx: Any, opts: ViewOptions, stop: threading.Event,
            ready: Callable[[str], None] | None) -> int:
    chans = SceneChannels(opts.map, ctx)
    changed = threading.Event()
    changed.set()
    events = client.watch(lambda _ev: changed.set())
    url = f"ws://{opts.host}:{server.port}"
    if ready is not None:
        ready(url)
    snap: SceneSnapshot | None = None
    shown_seq = -1
    last_fetch = last_publish = 0.0
    try:
        while not stop.is_set():
            now = time.monotonic()
            due = changed.is_set() or now - last_fetch >= opts.poll_s
            if due and now - last_fetch >= opts.min_interval_s:
                changed.clear()
                last_fetch = now
                try:
                    seq = client.info().seq
                    if seq != shown_seq:
                        mv = fetch_view(client, samples=opts.samples_per_frame > 0)
                        snap = build_snapshot(mv, time.time_ns(),
                                              samples_per_frame=opts.samples_per_frame)
                        shown_seq = mv.seq
                        chans.log(snap)
                        last_publish = time.monotonic()
                        log.info("map %r at seq %d: %d frames, %d components", mv.map, mv.seq,
                                 len(mv.frames), len(mv.components))
                except McsmError as exc:
                    log.warning("could not fetch the map (%s); trying again", exc)
                    changed.set()
            if snap is not None and time.monotonic() - last_publish >= opts.republish_s:
                chans.log(snap)
                last_publish = time.monotonic()
            stop.wait(0.05)
    finally:
        events.close()
    return 0
