"""A live view of the detector in Foxglove: camera image, matched place, inlier matches, plots.

:class:`LiveView` turns each frame's result into Foxglove messages, serialised once (protobuf
``foxglove.*`` schemas from foxglove-schemas-protobuf, JSON for the result and stats) and sent
to two optional sinks: a Foxglove WebSocket server (:class:`FoxgloveServer`, foxglove-sdk and,
for viewers of the older subprotocol, foxglove-websocket: the ``aefabmap[foxglove]`` extra,
imported only when a server is started) and the run's MCAP log
(``write_view``), so a saved log opens with the same layout (deploy/foxglove_layout.json).

Topics: ``/camera/image`` (foxglove.CompressedImage: JPEG/PNG as received, raw frames
JPEG-encoded), ``/lcd/place_image`` (the matched place's thumbnail), ``/lcd/annotations``
(foxglove.ImageAnnotations on the camera image: the best candidate's inlier points, when
VerificationConfig.keep_inlier_points is on, and a text line), ``/lcd/result`` and
``/lcd/stats`` (the JSON messages of runtime/aefabmap_runtime/core/records/messages.py, for Plot / Raw Messages).

The detector keeps no images: :class:`PlaceThumbnails` keeps one small JPEG per place
(longest side ``thumb_px``), following the map through ``inserted_place`` / ``evicted_place``
and bounded by ``max_bytes`` (oldest dropped first). Its memory cost is its bytes (a thumbnail's
size: docs/results.md, "Memory") plus ``pending`` recent frames' thumbnails waiting for their
(delayed) insertion.
"""

from __future__ import annotations

import base64
import json
import logging
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass

import cv2
import numpy as np
from foxglove_schemas_protobuf.Color_pb2 import Color
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations
from foxglove_schemas_protobuf.Point2_pb2 import Point2
from foxglove_schemas_protobuf.PointsAnnotation_pb2 import PointsAnnotation
from mcap_protobuf.schema import build_file_descriptor_set

from aefabmap_runtime.errors import ConfigError, TransportError
from aefabmap_runtime.adapters.foxglove_v1 import V1Channel
from aefabmap_runtime.adapters.frames import classify_encoding
from aefabmap_runtime.core.records.messages import FrameResult, StatsMessage

log = logging.getLogger("aefabmap.foxglove")

IMAGE_TOPIC = "/camera/image"
PLACE_IMAGE_TOPIC = "/lcd/place_image"
ANNOTATIONS_TOPIC = "/lcd/annotations"
RESULT_TOPIC = "/lcd/result"
STATS_TOPIC = "/lcd/stats"
DEFAULT_PORT = 8765
INSTALL_HINT = "the Foxglove live view needs foxglove-sdk: install aefabmap[foxglove]"
#: After a viewer's first subscription, time (s) left for its other ones: a viewer subscribes per
#: panel and the SDK reports each channel on its own.
VIEWER_SETTLE_S = 0.5
#: Slice (s) of the wait for a viewer between looks at the stop event.
_WAIT_SLICE_S = 0.1

#: Protobuf classes of the view's own topics (the MCAP writer registers their schemas).
VIEW_PROTOBUF = {PLACE_IMAGE_TOPIC: CompressedImage, ANNOTATIONS_TOPIC: ImageAnnotations}


@dataclass(frozen=True)
class LiveViewConfig:
    """thumb_px: longest side of a place thumbnail (px). thumb_quality: its JPEG quality.
    max_bytes: bound of the thumbnail store. pending: recent frames' thumbnails kept until the
    detector inserts them (its insertion delay must be shorter). jpeg_quality: encoding of raw
    live frames. frame_id: of the camera image (annotations refer to it)."""

    thumb_px: int = 160
    thumb_quality: int = 75
    max_bytes: int = 4 * 2**20
    pending: int = 64
    jpeg_quality: int = 80
    frame_id: str = "camera"

    def __post_init__(self) -> None:
        if not 16 <= self.thumb_px <= 1024:
            raise ConfigError(f"thumbnail size must be 16..1024 px, got {self.thumb_px!r}")
        if self.max_bytes < 0 or self.pending < 1:
            raise ConfigError("thumbnail store: max_bytes >= 0 and pending >= 1 required")


class PlaceThumbnails:
    """One JPEG thumbnail per place in the map, bounded by bytes (see the module docstring)."""

    def __init__(self, config: LiveViewConfig) -> None:
        self.config = config
        self._pending: OrderedDict[int, bytes] = OrderedDict()  # frame sequence -> JPEG
        self._places: OrderedDict[int, bytes] = OrderedDict()  # place id -> JPEG, oldest first
        self.nbytes = 0

    def __len__(self) -> int:
        return len(self._places)

    def get(self, place: int | None) -> bytes | None:
        return None if place is None else self._places.get(place)

    def observe(self, gray: np.ndarray, result: FrameResult) -> None:
        """Keep this frame's thumbnail until inserted; follow the map's insertion/eviction."""
        self._pending[result.sequence] = self.thumbnail(gray)
        while len(self._pending) > self.config.pending:
            self._pending.popitem(last=False)
        if result.evicted_place is not None:
            self._drop(result.evicted_place)
        if result.inserted_place is not None:
            frame = result.sequence if result.inserted_frame is None else result.inserted_frame
            thumb = self._pending.pop(frame, None)
            self._drop(result.inserted_place)  # an id being reused
            if thumb is not None:
                self._places[result.inserted_place] = thumb
                self.nbytes += len(thumb)
            while self.nbytes > self.config.max_bytes and self._places:
                self._drop(next(iter(self._places)))

    def _drop(self, place: int) -> None:
        old = self._places.pop(place, None)
        if old is not None:
            self.nbytes -= len(old)

    def thumbnail(self, gray: np.ndarray) -> bytes:
        h, w = gray.shape[:2]
        scale = self.config.thumb_px / max(h, w)
        if scale < 1:
            gray = cv2.resize(gray, (max(1, round(w * scale)), max(1, round(h * scale))), interpolation=cv2.INTER_AREA)
        ok, buf = cv2.imencode(".jpg", gray, [cv2.IMWRITE_JPEG_QUALITY, self.config.thumb_quality])
        return buf.tobytes() if ok else b""


def _stamp(msg, stamp_ns: int) -> None:
    msg.timestamp.FromNanoseconds(max(0, int(stamp_ns)))


def annotations_for(result: FrameResult, frame_id: str = "camera") -> ImageAnnotations:
    """The inlier points of the verified (else best) candidate on the live image, and one text
    line (place, score, inliers)."""
    msg = ImageAnnotations()
    cand = next((c for c in result.candidates if c.verified), None) or next(
        (c for c in result.candidates if c.inlier_points), None)
    if cand is not None and cand.inlier_points:
        pts = msg.points.add()
        _stamp(pts, result.stamp_ns)
        pts.type = PointsAnnotation.Type.POINTS
        pts.thickness = 4.0
        colour = (0.1, 0.9, 0.2, 1.0) if cand.verified else (1.0, 0.6, 0.0, 1.0)
        pts.outline_color.CopyFrom(Color(r=colour[0], g=colour[1], b=colour[2], a=colour[3]))
        pts.points.extend(Point2(x=float(p[0]), y=float(p[1])) for p in cand.inlier_points)
    text = msg.texts.add()
    _stamp(text, result.stamp_ns)
    text.position.CopyFrom(Point2(x=4.0, y=14.0))
    text.text = (f"{'LOOP ' if result.loop else ''}place {result.best_place} score {result.score:.3g} "
                 f"inliers {result.inliers} places {result.n_places}")
    text.font_size = 12.0
    text.text_color.CopyFrom(Color(r=1.0, g=1.0, b=1.0, a=1.0))
    text.background_color.CopyFrom(Color(r=0.0, g=0.0, b=0.0, a=0.6))
    return msg


def _subscription_listener(event: threading.Event):
    """A foxglove-sdk ServerListener that sets ``event`` when any viewer subscribes to any channel."""
    from foxglove.websocket import ServerListener

    class _Listener(ServerListener):  # the base class answers every other callback
        def on_subscribe(self, client, channel) -> None:
            event.set()

    return _Listener()


class FoxgloveServer:
    """A Foxglove WebSocket server (foxglove-sdk) with the view's channels, in its own context,
    behind one public port that also serves viewers of the older subprotocol.

    host: loopback by default (the protocol has no authentication). port: 0 picks a free one
    (``self.port`` tells). Raises ConfigError when foxglove-sdk is absent, TransportError when
    the port cannot be bound. foxglove-sdk accepts only the WebSocket subprotocol
    ``foxglove.sdk.v1``; it listens on a free loopback port behind ``host:port``
    (runtime/aefabmap_runtime/adapters/foxglove_front.py), where a viewer offering only
    ``foxglove.websocket.v1`` is served by foxglove-websocket instead (docs/streaming.md,
    "Which viewers connect").
    """

    def __init__(self, port: int = DEFAULT_PORT, host: str = "127.0.0.1", name: str = "aefabmap") -> None:
        if not isinstance(port, int) or not 0 <= port <= 65535:
            raise ConfigError(f"Foxglove port must be 0..65535, got {port!r}")
        try:
            import foxglove
        except ImportError as exc:
            raise ConfigError(INSTALL_HINT) from exc
        from aefabmap_runtime.adapters.foxglove_front import FoxgloveFront

        self._context = foxglove.Context()
        self.channels = {}
        v1_channels = []
        for topic, cls in ((IMAGE_TOPIC, CompressedImage), *VIEW_PROTOBUF.items()):
            descriptors = build_file_descriptor_set(cls).SerializeToString()
            schema = foxglove.Schema(name=cls.DESCRIPTOR.full_name, encoding="protobuf", data=descriptors)
            self.channels[topic] = foxglove.Channel(topic, schema=schema, message_encoding="protobuf",
                                                    context=self._context)
            v1_channels.append(V1Channel(topic, "protobuf", cls.DESCRIPTOR.full_name,
                                         base64.b64encode(descriptors).decode("ascii")))
        for topic, kind in ((RESULT_TOPIC, FrameResult), (STATS_TOPIC, StatsMessage)):
            text = json.dumps(kind.json_schema())
            schema = foxglove.Schema(name=kind.TITLE, encoding="jsonschema", data=text.encode())
            self.channels[topic] = foxglove.Channel(topic, schema=schema, message_encoding="json", context=self._context)
            v1_channels.append(V1Channel(topic, "json", kind.TITLE, text, "jsonschema"))
        self._viewer = threading.Event()
        try:  # the SDK on loopback only: viewers reach it through the public port
            self._server = foxglove.start_server(name=name, host="127.0.0.1", port=0, context=self._context,
                                                 server_listener=_subscription_listener(self._viewer))
        except Exception as exc:  # the SDK raises its own error types (bind failures)
            raise TransportError(f"cannot start the Foxglove server on 127.0.0.1: {exc}"[:300]) from exc
        try:
            self.front = FoxgloveFront(host, port, self._server.port, v1_channels, name, on_subscribe=self._viewer.set)
        except (OSError, TimeoutError) as exc:
            self._server.stop()
            raise TransportError(f"cannot start the Foxglove server on {host}:{port}: {exc}"[:300]) from exc
        if self.front.v1_missing is not None:
            log.warning("Foxglove viewers that speak only foxglove.websocket.v1 (Lichtblick up to 1.21) cannot "
                        "connect: %s; install aefabmap[foxglove]", self.front.v1_missing)
        self.port, self.host = self.front.port, host

    def subscribed(self, topic: str) -> bool:
        return self.channels[topic].has_sinks() or self.front.subscribed(topic)

    def wait_viewer(self, timeout_s: float, stop: threading.Event | None = None,
                    settle_s: float = VIEWER_SETTLE_S) -> bool:
        """Block until a viewer has subscribed to a channel, then ``settle_s`` (s) more for its other
        subscriptions. False when ``stop`` was set first; TransportError after ``timeout_s`` (s)."""
        stop = stop or threading.Event()
        deadline = time.monotonic() + timeout_s
        while not self._viewer.is_set():
            left = deadline - time.monotonic()
            if left <= 0:
                raise TransportError(f"no Foxglove viewer subscribed to ws://{self.host}:{self.port} "
                                     f"within {timeout_s:g} s")
            if stop.wait(min(left, _WAIT_SLICE_S)):
                return False
        return not stop.wait(settle_s)

    def log(self, topic: str, data: bytes, log_time_ns: int) -> None:
        self.channels[topic].log(data, log_time=log_time_ns)
        self.front.log(topic, data, log_time_ns)

    def stop(self) -> None:
        self._server.stop()  # first: its viewers get its close frames through the front
        self.front.stop()


class LiveView:
    """Foxglove messages of each frame to a server and/or the log (see the module docstring).

    server: a FoxgloveServer or None. log: anything with ``write_view(topic, data, stamp_ns,
    sequence)`` (McapLogWriter, RotatingLog) or None; set later with ``attach_log``.
    """

    def __init__(self, server: FoxgloveServer | None = None, config: LiveViewConfig | None = None,
                 log=None) -> None:
        self.server, self.config, self.log = server, config or LiveViewConfig(), log
        self.thumbnails = PlaceThumbnails(self.config)
        self.frames = 0

    def attach_log(self, log) -> None:
        self.log = log

    def wait_viewer(self, timeout_s: float, stop: threading.Event | None = None) -> bool:
        """FoxgloveServer.wait_viewer of the view's server (ConfigError without one)."""
        if self.server is None:
            raise ConfigError("waiting for a viewer needs the Foxglove server")
        return self.server.wait_viewer(timeout_s, stop)

    def _send(self, topic: str, data: bytes, stamp_ns: int, sequence: int, *, to_log: bool = True) -> None:
        if self.server is not None:
            self.server.log(topic, data, stamp_ns)
        if to_log and self.log is not None:
            self.log.write_view(topic, data, stamp_ns, sequence=sequence)

    def on_frame(self, payload: bytes, encoding: str, gray: np.ndarray | None, result: FrameResult,
                 data: bytes | None = None) -> None:
        """One processed frame: payload/encoding as received, gray its decoded (H, W) uint8
        image, data the result's JSON when already serialised (the log has it already)."""
        self.frames += 1
        stamp, seq = result.stamp_ns, result.sequence
        place = result.verified_place if result.verified_place is not None else result.best_place
        thumb = self.thumbnails.get(place)  # before this frame changes the map's ids
        if gray is not None:
            self.thumbnails.observe(gray, result)
        if self.server is not None:  # the log has the camera image and the result already
            # (no client watching the image: do not build it; a raw frame costs a JPEG encode)
            if self.server.subscribed(IMAGE_TOPIC) and (image := self._camera_image(payload, encoding, gray, stamp)):
                self.server.log(IMAGE_TOPIC, image, stamp)
            self.server.log(RESULT_TOPIC, data if data is not None else result.to_json_bytes(), stamp)
        self._send(ANNOTATIONS_TOPIC, annotations_for(result, self.config.frame_id).SerializeToString(), stamp, seq)
        if thumb is not None:
            msg = CompressedImage(frame_id="place", data=thumb, format="jpeg")
            _stamp(msg, stamp)
            self._send(PLACE_IMAGE_TOPIC, msg.SerializeToString(), stamp, seq)

    def on_stats(self, data: bytes, stamp_ns: int) -> None:
        if self.server is not None:
            self.server.log(STATS_TOPIC, data, stamp_ns)

    def _camera_image(self, payload: bytes, encoding: str, gray: np.ndarray | None, stamp_ns: int) -> bytes:
        kind, _ = classify_encoding(encoding)
        if kind == "raw":
            if gray is None:
                return b""
            ok, buf = cv2.imencode(".jpg", gray, [cv2.IMWRITE_JPEG_QUALITY, self.config.jpeg_quality])
            if not ok:
                return b""
            payload, kind = buf.tobytes(), "jpeg"
        msg = CompressedImage(frame_id=self.config.frame_id, data=bytes(payload), format=kind)
        _stamp(msg, stamp_ns)
        return msg.SerializeToString()

    def close(self) -> None:
        if self.server is not None:
            self.server.stop()
