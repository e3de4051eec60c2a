"""A WebSocket relay that lets every Foxglove client in: ``foxglove.sdk.v1`` and the older name
``foxglove.websocket.v1`` of the same protocol.

foxglove-sdk's server (0.30) accepts only ``foxglove.sdk.v1`` and answers HTTP 400 to a client
that offers only ``foxglove.websocket.v1``: the default of npm's ``@foxglove/ws-protocol``
client, Lichtblick before December 2025, roslibjs-foxglove. Foxglove states that the two
names denote the same protocol (foxglove discussion 1131; Lichtblick's pull request 819 adds
the new name beside the old for that reason). So ``mcsm view`` runs the sdk's server on a
private loopback port and this relay on the public one: it accepts either name (preferring
``foxglove.sdk.v1``), opens one upstream connection per client with ``foxglove.sdk.v1``, and
copies every frame both ways unchanged (text frames stay text, binary stay binary). A client
offering neither name gets HTTP 400, as from the sdk.

Needs ``websockets`` (the ``viz`` extra). Runs its own asyncio loop in a daemon thread.
"""

from __future__ import annotations

import asyncio
import logging
import threading
from typing import Any

log = logging.getLogger("mcsm.view.relay")

#: accepted subprotocols, the preferred first
SUBPROTOCOLS = ("foxglove.sdk.v1", "foxglove.websocket.v1")
UPSTREAM_SUBPROTOCOL = "foxglove.sdk.v1"


class FoxgloveRelay:
    """Listen on ``host:port`` and relay each client to ``upstream`` (``ws://...``).

    :meth:`start` returns once listening (the port, when ``port`` was 0); :meth:`stop` closes
    the listener and every relayed connection.

    Raises
    ------
    OSError
        From :meth:`start`, if the port cannot be bound.
    """

    def __init__(self, host: str, port: int, upstream: str) -> None:
        self.host = host
        self.port = port
        self.upstream = upstream
        self.clients = 0  # connections accepted so far
        self.subprotocols_seen: dict[str, int] = {}
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, name="foxglove-relay",
                                        daemon=True)
        self._server: Any = None

    def start(self) -> int:
        from websockets.asyncio.server import serve
        from websockets.typing import Subprotocol

        self._thread.start()

        async def listen() -> Any:
            return await serve(self._handle, self.host, self.port,
                               subprotocols=[Subprotocol(s) for s in SUBPROTOCOLS],
                               max_size=None, compression=None)

        try:
            self._server = asyncio.run_coroutine_threadsafe(listen(), self._loop).result(30)
        except BaseException:
            self._loop.call_soon_threadsafe(self._loop.stop)
            self._thread.join(5)
            raise
        self.port = int(next(iter(self._server.sockets)).getsockname()[1])
        return self.port

    async def _handle(self, down: Any) -> None:
        from websockets.asyncio.client import connect
        from websockets.exceptions import WebSocketException
        from websockets.typing import Subprotocol

        self.clients += 1
        proto = str(down.subprotocol)
        self.subprotocols_seen[proto] = self.subprotocols_seen.get(proto, 0) + 1
        log.info("client %s connected with %s", down.remote_address, proto)
        try:
            async with connect(self.upstream, subprotocols=[Subprotocol(UPSTREAM_SUBPROTOCOL)],
                               max_size=None, compression=None, open_timeout=10) as up:
                pumps = [asyncio.create_task(self._pump(down, up)),
                         asyncio.create_task(self._pump(up, down))]
                _done, pending = await asyncio.wait(pumps, return_when=asyncio.FIRST_COMPLETED)
                for t in pending:
                    t.cancel()
        except (OSError, TimeoutError, WebSocketException) as exc:
            log.warning("relay to %s ended: %s", self.upstream, exc)

    @staticmethod
    async def _pump(src: Any, dst: Any) -> None:
        from websockets.exceptions import ConnectionClosed

        try:
            async for msg in src:
                await dst.send(msg)
        except ConnectionClosed:
            pass
        finally:
            await dst.close()

    def stop(self) -> None:
        """Close the listener and its connections; idempotent."""
        if self._server is None or not self._thread.is_alive():
            return

        async def close() -> None:
            self._server.close()
            await self._server.wait_closed()

        try:
            asyncio.run_coroutine_threadsafe(close(), self._loop).result(10)
        except (TimeoutError, RuntimeError) as exc:
            log.warning("closing the relay: %s", exc)
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(10)
