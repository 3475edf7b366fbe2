"""The live view's public port, for viewers of both Foxglove WebSocket subprotocols.

foxglove-sdk's server accepts only ``foxglove.sdk.v1`` (a fixed constant of the SDK: no option
changes it) and answers HTTP 400 to a viewer that offers only ``foxglove.websocket.v1``. So the
port the user gives is ours: :class:`SubprotocolRouter` reads each connection's HTTP upgrade
request and splices the connection, that request included, to one of two servers on loopback:
the v1 server (foxglove_v1.py) when the viewer offers ``foxglove.websocket.v1`` and not
``foxglove.sdk.v1``, else the SDK's (which answers whatever it does not speak as before).

Hostile clients: a request head longer than HEAD_LIMIT bytes or slower than HEAD_TIMEOUT_S, and
connections beyond MAX_CONNECTIONS, are closed and counted in ``problems``; never raised.

:class:`FoxgloveFront` runs the router and the v1 server in one asyncio loop on its own thread.
"""

from __future__ import annotations

import asyncio
import logging
import socket
import threading
from collections import Counter
from collections.abc import Callable

from aefabmap_runtime.adapters.foxglove_v1 import V1_SUBPROTOCOL, V1Channel, V1Server

SDK_SUBPROTOCOL = "foxglove.sdk.v1"
#: Longest HTTP upgrade request read before routing (bytes), and the time allowed for it (s).
HEAD_LIMIT = 16 * 1024
HEAD_TIMEOUT_S = 10.0
#: Viewer connections open at once; more are closed at once.
MAX_CONNECTIONS = 32
#: After one side of a spliced connection ended, time (s) left to the other to finish (a close handshake).
_DRAIN_S = 5.0
#: At stop, time (s) the connections get to carry the servers' close frames before they are cut.
_CLOSE_GRACE_S = 1.0
_CHUNK = 64 * 1024

log = logging.getLogger("aefabmap.foxglove")


def offered_subprotocols(head: bytes) -> list[str]:
    """The subprotocols an HTTP upgrade request offers, in order (every Sec-WebSocket-Protocol header)."""
    offered: list[str] = []
    for line in head.split(b"\r\n")[1:]:
        name, sep, value = line.partition(b":")
        if sep and name.strip().lower() == b"sec-websocket-protocol":
            offered += [t.strip() for t in value.decode("latin-1").split(",") if t.strip()]
    return offered


def speaks_v1_only(head: bytes) -> bool:
    """True when the request offers ``foxglove.websocket.v1`` and not ``foxglove.sdk.v1``."""
    offered = offered_subprotocols(head)
    return V1_SUBPROTOCOL in offered and SDK_SUBPROTOCOL not in offered


def bind_listener(host: str, port: int) -> socket.socket:
    """A listening TCP socket on the first address of ``host`` (one port even for a name that
    resolves to several addresses; "": every interface). OSError when it cannot bind."""
    family, kind, proto, _name, address = socket.getaddrinfo(host or None, port, type=socket.SOCK_STREAM,
                                                             flags=socket.AI_PASSIVE)[0]
    sock = socket.socket(family, kind, proto)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(address)
        sock.listen(64)
        sock.setblocking(False)
    except BaseException:
        sock.close()
        raise
    return sock


class SubprotocolRouter:
    """Splices each connection on ``sock`` to loopback ``sdk_port`` or ``v1_port`` (None: no v1
    server) by the subprotocols it offers (see the module docstring). Runs on the running loop."""

    def __init__(self, sock: socket.socket, sdk_port: int, v1_port: int | None) -> None:
        self.sock, self.sdk_port, self.v1_port = sock, sdk_port, v1_port
        self.problems: Counter = Counter()
        self.routed: Counter = Counter()  # subprotocol family -> connections
        self._tasks: set[asyncio.Task] = set()
        self._server: asyncio.base_events.Server | None = None

    async def start(self) -> None:
        self._server = await asyncio.start_server(self._accept, sock=self.sock, limit=HEAD_LIMIT)

    def _accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if len(self._tasks) >= MAX_CONNECTIONS:
            self.problems["too_many_connections"] += 1
            writer.close()
            return
        task = asyncio.get_running_loop().create_task(self._serve(reader, writer))
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        upstream = None
        try:
            try:
                head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), HEAD_TIMEOUT_S)
            except asyncio.TimeoutError:
                self.problems["slow_request"] += 1
                return
            except asyncio.LimitOverrunError:
                self.problems["long_request"] += 1
                return
            except asyncio.IncompleteReadError:
                self.problems["incomplete_request"] += 1
                return
            v1 = self.v1_port is not None and speaks_v1_only(head)
            self.routed["v1" if v1 else "sdk"] += 1
            up_reader, upstream = await asyncio.open_connection("127.0.0.1", self.v1_port if v1 else self.sdk_port)
            upstream.write(head)
            await _splice(reader, writer, up_reader, upstream)
        except (ConnectionError, OSError) as exc:  # a viewer gone, or an inner server stopping
            self.problems["connection_lost"] += 1
            log.debug("Foxglove router: %s", exc)
        finally:
            for w in (writer, upstream):
                if w is not None:
                    w.close()

    def stop_listening(self) -> None:
        if self._server is not None:
            self._server.close()

    async def close(self, grace_s: float = _CLOSE_GRACE_S) -> None:
        """Stop listening; connections still open after ``grace_s`` (s) are cut (the servers
        behind, stopped first, have sent their close frames through them by then)."""
        self.stop_listening()
        if self._tasks:
            await asyncio.wait(list(self._tasks), timeout=grace_s)
        for task in list(self._tasks):
            task.cancel()
        if self._tasks:
            await asyncio.wait(list(self._tasks), timeout=_DRAIN_S)
        if self._server is not None:
            await self._server.wait_closed()


async def _pipe(src: asyncio.StreamReader, dst: asyncio.StreamWriter) -> None:
    """Copy until the end of src, then half-close dst; a slow dst slows the copy (drain)."""
    while data := await src.read(_CHUNK):
        dst.write(data)
        await dst.drain()
    if dst.can_write_eof():
        dst.write_eof()


async def _splice(client_r, client_w, up_r, up_w) -> None:
    """Both directions until both end; once one has ended, the other gets _DRAIN_S to end."""
    tasks = [asyncio.create_task(_pipe(client_r, up_w)), asyncio.create_task(_pipe(up_r, client_w))]
    try:
        done, pending = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        if pending and not any(t.exception() for t in done):
            done, pending = await asyncio.wait(pending, timeout=_DRAIN_S)
        for task in done:
            if task.exception() is not None:
                raise task.exception()
    finally:
        for task in tasks:
            task.cancel()


class FoxgloveFront:
    """The public port of the live view on ``host:port`` (0: a free one; ``self.port`` tells), in
    front of the SDK server on loopback ``sdk_port``, with a v1 server of ``channels``.

    on_subscribe: called when a v1 viewer subscribes. OSError when the port cannot be bound.
    Without foxglove-websocket the v1 server is left out (``v1_missing`` says why) and every
    viewer goes to the SDK server.
    """

    def __init__(self, host: str, port: int, sdk_port: int, channels: list[V1Channel], name: str,
                 on_subscribe: Callable[[], None] = lambda: None, start_timeout_s: float = 10.0) -> None:
        sock = bind_listener(host, port)
        self.port = sock.getsockname()[1]
        self.v1: V1Server | None = None
        self.v1_missing: str | None = None
        try:
            self.v1 = V1Server(channels, name, on_subscribe)
        except ImportError as exc:
            self.v1_missing = f"foxglove-websocket is not installed ({exc})"
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, name="foxglove-front", daemon=True)
        self._thread.start()
        self.router: SubprotocolRouter | None = None
        try:
            self._run(self._start(sock, sdk_port), start_timeout_s)
        except BaseException:
            sock.close()
            self.stop()
            raise

    def _run(self, coro, timeout_s: float):
        return asyncio.run_coroutine_threadsafe(coro, self._loop).result(timeout_s)

    async def _start(self, sock: socket.socket, sdk_port: int) -> None:
        v1_port = await self.v1.start() if self.v1 is not None else None
        self.router = SubprotocolRouter(sock, sdk_port, v1_port)
        await self.router.start()

    def subscribed(self, topic: str) -> bool:
        return self.v1 is not None and self.v1.subscribed(topic)

    def log(self, topic: str, data: bytes, log_time_ns: int) -> None:
        if self.v1 is not None:
            self.v1.log(topic, data, log_time_ns)

    def stop(self, timeout_s: float = 10.0) -> None:
        """Close the port, the v1 server and the viewers' connections; end the thread. Stop the
        SDK server first: its viewers then get its close frames, not a reset."""
        if self._loop.is_closed():
            return
        if self._thread.is_alive():
            try:
                self._run(self._close(), timeout_s)
            except Exception as exc:  # stopping goes on: the thread is a daemon
                log.debug("Foxglove front: stop: %s", exc)
            self._loop.call_soon_threadsafe(self._loop.stop)
            self._thread.join(timeout_s)
        if not self._thread.is_alive():
            self._loop.close()

    async def _close(self) -> None:
        if self.router is not None:
            self.router.stop_listening()
        if self.v1 is not None:
            await self.v1.close()
        if self.router is not None:
            await self.router.close()
        # Whatever the servers left running ends here, not with the loop (no "Task was destroyed").
        others = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
        for task in others:
            task.cancel()
        if others:
            await asyncio.wait(others, timeout=_DRAIN_S)
