"""The live view's channels for viewers that speak only ``foxglove.websocket.v1``.

foxglove-sdk's server speaks ``foxglove.sdk.v1`` only; Lichtblick up to 1.21 and older Foxglove
Studio offer ``foxglove.websocket.v1`` only (the protocol of foxglove/ws-protocol docs/spec.md).
:class:`V1Server` serves them with Foxglove's own implementation of that protocol
(foxglove-websocket, part of the ``aefabmap[foxglove]`` extra) on a free loopback port, in an
asyncio loop the caller runs (runtime/aefabmap_runtime/adapters/foxglove_front.py routes the
view's public port to it). Messages are sent only on channels a viewer subscribed to; at most
MAX_PENDING wait to be sent, newer ones are dropped and counted (a slow viewer never holds the
detector up).
"""

from __future__ import annotations

import asyncio
import logging
import threading
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass

V1_SUBPROTOCOL = "foxglove.websocket.v1"
#: Messages waiting to be sent to the v1 viewers; past this, new ones are dropped.
MAX_PENDING = 128
#: Largest message a v1 viewer may send (bytes): subscriptions are small.
MAX_CLIENT_MESSAGE = 64 * 1024
#: At stop, time (s) a viewer gets to answer the close handshake, and the longest stop.
CLOSE_TIMEOUT_S = 1.0
STOP_TIMEOUT_S = 3.0

log = logging.getLogger("aefabmap.foxglove")


@dataclass(frozen=True)
class V1Channel:
    """One channel as the v1 protocol advertises it: schema is the text the spec asks for (base64
    of the FileDescriptorSet for protobuf, the JSON schema for json)."""

    topic: str
    encoding: str
    schema_name: str
    schema: str
    schema_encoding: str | None = None

    def advertised(self) -> dict:
        doc = {"topic": self.topic, "encoding": self.encoding, "schemaName": self.schema_name, "schema": self.schema}
        if self.schema_encoding is not None:
            doc["schemaEncoding"] = self.schema_encoding
        return doc


def import_v1_server():
    """foxglove-websocket's server and listener classes (ImportError when absent). It is written on
    the legacy API of `websockets`, whose DeprecationWarnings Python hides outside tests."""
    from foxglove_websocket.server import FoxgloveServer, FoxgloveServerListener

    return FoxgloveServer, FoxgloveServerListener


class _OneLineLog:
    """The logger handed to foxglove-websocket: whatever a viewer sends that it cannot use is one
    DEBUG line here (no traceback) and counted under ``problems``."""

    def __init__(self, problems: Counter) -> None:
        self.problems = problems

    def debug(self, msg, *args, **_kw) -> None:
        log.debug("v1 server: " + str(msg), *args)

    info = debug

    def error(self, msg, *args, **_kw) -> None:
        self.problems["viewer_error"] += 1
        log.debug("v1 server: " + str(msg), *args)

    exception = warning = error


def _websockets_logger(problems: Counter) -> logging.Logger:
    """The logger handed to `websockets` under foxglove-websocket: a failed handshake or a broken
    connection is one DEBUG line on ours and counted (it would log a traceback at ERROR)."""

    class _OneLine(logging.Filter):
        def filter(self, record: logging.LogRecord) -> bool:
            if record.levelno >= logging.ERROR:
                problems["connection_error"] += 1
            log.debug("v1 websocket: %s", record.getMessage())
            return False  # never handled further

    # Unregistered: this server's own. INFO: `websockets` would format a DEBUG line per frame.
    logger = logging.Logger("aefabmap.foxglove.websockets", logging.INFO)
    logger.addFilter(_OneLine())
    return logger


class V1Server:
    """The view's channels over ``foxglove.websocket.v1`` on 127.0.0.1 (see the module docstring).

    Build it, then ``await start(loop)`` on the loop that will run it; ``log``, ``subscribed`` and
    ``dropped`` may be used from any thread. on_subscribe: called (on the loop's thread) when a
    viewer subscribes to a channel no viewer had. ImportError when foxglove-websocket is absent.
    """

    def __init__(self, channels: list[V1Channel], name: str, on_subscribe: Callable[[], None] = lambda: None) -> None:
        self._server_cls, listener_cls = import_v1_server()
        self.channels, self.name, self.on_subscribe = channels, name, on_subscribe
        self.problems: Counter = Counter()
        self.port = 0
        self.dropped = 0
        self._ids: dict[str, int] = {}
        self._topics: dict[int, str] = {}
        self._subscribed: frozenset[str] = frozenset()
        self._pending = 0
        self._lock = threading.Lock()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._queue: asyncio.Queue | None = None
        self._sender: asyncio.Task | None = None
        self._server = None
        owner = self

        class _Listener(listener_cls):
            def on_subscribe(self, server, channel_id) -> None:
                owner._follow(channel_id, True)

            def on_unsubscribe(self, server, channel_id) -> None:
                owner._follow(channel_id, False)

        self._listener = _Listener()

    async def start(self, timeout_s: float = 10.0) -> int:
        """Listen on a free loopback port and advertise the channels; the port. OSError/TimeoutError
        when it cannot listen."""
        self._loop = asyncio.get_running_loop()
        self._queue = asyncio.Queue()
        self._server = self._server_cls("127.0.0.1", 0, self.name, logger=_OneLineLog(self.problems),
                                        server_kwargs={"compression": None, "max_size": MAX_CLIENT_MESSAGE,
                                                       "close_timeout": CLOSE_TIMEOUT_S,
                                                       "logger": _websockets_logger(self.problems)})
        self._server.set_listener(self._listener)
        self._server.start()
        opened = await asyncio.wait_for(self._server.wait_opened(), timeout_s)
        for channel in self.channels:
            cid = await self._server.add_channel(channel.advertised())
            self._ids[channel.topic], self._topics[cid] = cid, channel.topic
        self._sender = asyncio.create_task(self._send_pending())
        self.port = opened.sockets[0].getsockname()[1]
        return self.port

    def _follow(self, channel_id: int, subscribed: bool) -> None:
        topic = self._topics.get(channel_id)
        if topic is None:
            return
        self._subscribed = self._subscribed | {topic} if subscribed else self._subscribed - {topic}
        if subscribed:
            self.on_subscribe()

    def subscribed(self, topic: str) -> bool:
        return topic in self._subscribed

    def log(self, topic: str, data: bytes, log_time_ns: int) -> None:
        """Send one message on ``topic`` to its v1 viewers (none subscribed: nothing; too many
        waiting: dropped and counted). Any thread."""
        if topic not in self._subscribed or self._loop is None:
            return
        with self._lock:
            if self._pending >= MAX_PENDING:
                self.dropped += 1
                return
            self._pending += 1
        try:
            self._loop.call_soon_threadsafe(self._queue.put_nowait, (self._ids[topic], log_time_ns, bytes(data)))
        except RuntimeError:  # the loop is closed: the view is stopping
            with self._lock:
                self._pending -= 1

    async def _send_pending(self) -> None:
        while True:  # one sender: messages reach every viewer in the order they were logged
            channel_id, log_time_ns, data = await self._queue.get()
            try:
                await self._server.send_message(channel_id, log_time_ns, data)
            except Exception as exc:  # a viewer gone mid-send: its loss, not the view's
                self.problems["send_failed"] += 1
                log.debug("v1 server: send failed: %s", exc)
            finally:
                with self._lock:
                    self._pending -= 1

    async def close(self) -> None:
        """Stop listening, close the viewers' connections (at most STOP_TIMEOUT_S) and the sender."""
        if self._sender is not None:
            self._sender.cancel()
        if self._server is not None:
            self._server.close()
            try:
                await asyncio.wait_for(self._server.wait_closed(), STOP_TIMEOUT_S)
            except asyncio.TimeoutError:  # a viewer that never answers: the front cuts it
                self.problems["slow_close"] += 1
