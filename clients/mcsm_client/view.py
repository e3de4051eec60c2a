"""``mcsm view``: follow a live map over Zenoh and serve it to Foxglove (and Lichtblick).

A separate process (the server stays headless), a client of the map like any other: a
``MapClient`` subscribes to ``<prefix>/<map>/events``; after each change (at most every
``min_interval_s``, and every ``poll_s`` in case an event was missed, since events are best
effort) it asks ``info`` for the components, fetches each one with the submap export RPC,
rebuilds a local copy of the map with ``StochasticMap.import_component`` and publishes the scene
of :mod:`mcsm.viz.foxglove_scene` through foxglove-sdk's WebSocket server. The last scene is
published again every ``republish_s`` so that a viewer connecting later sees the map at once.

Besides the scene: every event becomes a ``foxglove.Log`` line on ``/mcsm/<map>/log`` (the
update's frames, kind, verdict with its NIS and threshold, request id; a rejected or held
constraint is a warning), and the map's counters (updates per verdict, frames, components,
refused requests, queue length) go on ``/mcsm/<map>/stats`` at each refresh, for Foxglove's
Plot panel. ``docs/foxglove-layout.json`` arranges all of it.

Viewers connect through :class:`mcsm_client.foxglove_relay.FoxgloveRelay`, which accepts the
``foxglove.websocket.v1`` subprotocol as well as ``foxglove.sdk.v1`` (the sdk's own server
takes only the latter). Reads only: the view never writes to the map. This module lives in the
client package (it is a client); ``mcsm view`` reaches it through the entry-point group
``mcsm.commands`` (:mod:`mcsm_client.commands`).
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from mcsm import wire
from mcsm.errors import McsmError
from mcsm.viz.foxglove_scene import (
    DEFAULT_SAMPLES_PER_FRAME,
    SceneChannels,
    SceneSnapshot,
    build_snapshot,
    load_foxglove,
    map_stats,
    verdict_text,
)
from mcsm.viz.scene import MapView, map_view

from mcsm_client.client import MapClient

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


def fetch_view(client: MapClient, samples: bool,
               parents: dict[str, str] | None = None) -> tuple[MapView, wire.MapInfo]:
    """The map behind ``client`` now, rebuilt locally from one export per component, and the
    ``info`` it was built from.

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
    return map_view(local, map_name=info.map, seq=info.seq, samples=samples,
                    parents=parents), info


def stats_of(info: wire.MapInfo) -> dict[str, int]:
    """The ``mcsm.MapStats`` counters of an ``info`` reply."""
    return map_stats(info.seq, info.n_frames, len(info.components), dict(info.verdicts),
                     info.rejected, info.queue_length)


def event_lines(ev: wire.Event) -> list[tuple[str, str]]:
    """``(level, text)`` log lines of one event: its own, and one per held closure it
    decided (``extra.changed``)."""
    extra = ev.extra or {}
    v = extra.get("verdict")
    out = [verdict_text(ev.seq, ev.op, ev.kind, tuple(ev.frames),
                        v if isinstance(v, dict) else None, ev.request_id)]
    changed = extra.get("changed")
    if isinstance(changed, dict):
        for rid, cv in changed.items():
            if isinstance(cv, dict):
                level, text = verdict_text(ev.seq, "decided", str(cv.get("status", "")), (),
                                           cv, str(rid))
                out.append((level, text.replace(f"seq {ev.seq} decided :", f"seq {ev.seq}: "
                                                "held closure decided:", 1)))
    return out


class _Parents:
    """Which frame each new frame was created from, learnt from update events (the robot
    paths; frames created before the view started fall back to their names)."""

    def __init__(self) -> None:
        self.parent: dict[str, str] = {}
        self.known: set[str] = set()

    def event(self, ev: wire.Event) -> None:
        if ev.op != "update" or len(ev.frames) != 2:
            return
        a, b = ev.frames
        if ev.kind == "new_component" or (ev.kind == "new_frame" and a in self.known):
            self.parent.setdefault(b, a)
        elif ev.kind == "new_frame" and b in self.known:
            self.parent.setdefault(a, b)
        self.known.update((a, b))


def run_view(opts: ViewOptions, stop: threading.Event,
             ready: Callable[[str], None] | None = None) -> int:
    """Serve the live scene until ``stop`` is set; returns 0.

    ``ready`` is called once with the WebSocket URL when the relay listens.

    Raises
    ------
    McsmError
        No server answers within ``opts.timeout_s``, or the WebSocket port cannot be opened.
    """
    from mcsm_client.foxglove_relay import FoxgloveRelay

    fg = load_foxglove()
    try:
        import websockets  # noqa: F401 - the relay's; said at once when missing
    except ImportError:
        from mcsm.viz import MissingExtra

        raise MissingExtra("websockets") from None
    where = opts.connect or "the configured endpoints"
    try:
        client = MapClient(map=opts.map, connect=opts.connect, zenoh_config=opts.zenoh_config,
                           timeout_s=opts.timeout_s, prefix=opts.prefix)
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
            server = fg.start_server(name=f"mcsm view {opts.map}", host="127.0.0.1", port=0,
                                     context=ctx)
        except Exception as exc:  # foxglove raises its own error types for bind failures
            raise McsmError(f"cannot start the Foxglove WebSocket server: {exc}") from None
        relay = FoxgloveRelay(opts.host, opts.foxglove_port, f"ws://127.0.0.1:{server.port}")
        try:
            try:
                relay.start()
            except OSError as exc:
                raise McsmError(f"cannot start the Foxglove WebSocket server on "
                                f"{opts.host}:{opts.foxglove_port}: "
                                f"{exc.strerror or exc}") from None
            return _follow(client, relay, ctx, opts, stop, ready)
        finally:
            relay.stop()
            server.stop()
    finally:
        client.close()


def _follow(client: MapClient, relay: Any, ctx: Any, opts: ViewOptions, stop: threading.Event,
            ready: Callable[[str], None] | None) -> int:
    chans = SceneChannels(opts.map, ctx)
    changed = threading.Event()
    changed.set()
    pending: queue.Queue[wire.Event] = queue.Queue(maxsize=10_000)
    parents = _Parents()

    def on_event(ev: wire.Event) -> None:
        try:
            pending.put_nowait(ev)
        except queue.Full:
            pass  # events are best effort; the next refresh shows the map anyway
        changed.set()

    events = client.watch(on_event)
    url = f"ws://{opts.host}:{relay.port}"
    if ready is not None:
        ready(url)
    snap: SceneSnapshot | None = None
    shown_seq = -1
    last_fetch = last_publish = 0.0
    try:
        while not stop.is_set():
            while True:
                try:
                    ev = pending.get_nowait()
                except queue.Empty:
                    break
                parents.event(ev)
                for level, text in event_lines(ev):
                    chans.log_line(ev.time_ns, level, text, stamp=False)
            now = time.monotonic()
            due = changed.is_set() or now - last_fetch >= opts.poll_s
            if due and now - last_fetch >= opts.min_interval_s:
                changed.clear()
                last_fetch = now
                try:
                    info = client.info()
                    if info.seq != shown_seq:
                        mv, info = fetch_view(client, opts.samples_per_frame > 0,
                                              parents.parent)
                        parents.known.update(info.frames)
                        snap = build_snapshot(mv, time.time_ns(),
                                              samples_per_frame=opts.samples_per_frame)
                        shown_seq = mv.seq
                        log.info("map %r at seq %d: %d frames, %d components", mv.map,
                                 mv.seq, len(mv.frames), len(mv.components))
                    if snap is not None:
                        snap.stats = stats_of(info)
                        chans.log(snap)
                        last_publish = time.monotonic()
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
