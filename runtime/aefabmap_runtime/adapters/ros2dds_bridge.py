"""ROS 2 over DDS (Fast DDS, Cyclone DDS) through zenoh-bridge-ros2dds: read and write its keys.

What the bridge (eclipse-zenoh/zenoh-plugin-ros2dds: README, DEFAULT_CONFIG.json5, sources) puts
on Zenoh, and what this module relies on:

- key: a ROS topic ``/camera/image_raw`` is the key ``camera/image_raw``; a bridge given a
  namespace (``-n /bot1``, or ``namespace`` in its config) prefixes every name with it, absolute
  ones too: ``bot1/camera/image_raw``. The key holds no domain (the bridge serves one DDS domain),
  no type and no type hash;
- payload: the DDS sample as it is, CDR with its 4-byte encapsulation header (ros_cdr.py), and no
  attachment: no sequence numbers, so drops cannot be counted (frames are ``unsequenced``);
- the other way: a publication on ``lcd/result`` reaches the DDS subscribers of ``/lcd/result``
  behind the bridge (it routes a topic from Zenoh to DDS once a DDS reader of it exists, with
  that reader's type);
- graph: each DDS publisher the bridge routes is announced by a liveliness token
  ``@/<bridge zid>/@ros2_lv/MP/<key>/<type>/<qos>``, ``/`` in key and type written ``§``.

The image type is not in the key: a sample is read as sensor_msgs/Image, else as
CompressedImage (the strict CDR reader refuses the other layout). Results and stats go out as on
the plain keys (JSON) and as std_msgs/String (the same JSON) and diagnostic_msgs/DiagnosticArray
on the bridge's keys of ``/lcd/result``, ``/lcd/stats`` and ``/diagnostics``.
"""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Callable

import zenoh

from aefabmap_runtime.adapters.frames import FrameError
from aefabmap_runtime.adapters.rmw_zenoh import (
    DIAGNOSTICS_TOPIC,
    MAX_GRAPH_TOKENS,
    RosOptions,
    TopicPublisher,
    bridge_key,
)
from aefabmap_runtime.adapters.ros_cdr import (
    COMPRESSED_IMAGE_TYPE,
    IMAGE_TYPE,
    RosImage,
    decode_compressed_cdr,
    decode_image_cdr,
    encode_string_cdr,
)
from aefabmap_runtime.adapters.ros_diagnostics import diagnostics_cdr, json_text
from aefabmap_runtime.adapters.zenoh_transport import DropCounter, FrameMeta, ReceivedFrame, poll_ring
from aefabmap_runtime.errors import ConfigError, TransportError

#: Where the bridge announces the DDS publishers it routes (liveliness tokens).
PUBLISHER_TOKENS = "@/*/@ros2_lv/MP/**"
#: What the bridge writes for ``/`` inside a key or type chunk of a token.
SLASH = "§"


def home_of(namespace: str) -> str:
    """How a warning names the bridge's side of the run: ``zenoh-bridge-ros2dds namespace /bot1``."""
    return f"zenoh-bridge-ros2dds namespace /{namespace.strip('/')}"


def decode_bridge_image(data: bytes) -> tuple[RosImage, str]:
    """A bridged sample as (image, its message type): sensor_msgs/Image, else CompressedImage.
    FrameError when it is neither (the Image reading's error, unless the CompressedImage
    reading got past the CDR and failed on the image itself)."""
    try:
        return decode_image_cdr(data), IMAGE_TYPE
    except FrameError as exc:
        if exc.reason != "corrupt":
            raise
        as_image = exc
    try:
        return decode_compressed_cdr(data), COMPRESSED_IMAGE_TYPE
    except FrameError as exc:
        raise as_image if exc.reason == "corrupt" else exc from None


class BridgeFrameSubscriber:
    """Subscribes to a ROS 2 image topic's key on zenoh-bridge-ros2dds; same interface as
    FrameSubscriber. ``receive`` returns a ReceivedFrame whose payload/encoding follow the frames
    contract (decoded from CDR here), its ``error`` the FrameError of a message that could not be
    used; the frame stamp is the header's (else the receive time). ``ros_type``: the first image's."""

    def __init__(self, session: zenoh.Session, key: str, *, queue_size: int = 2, poll_s: float = 0.002) -> None:
        if not isinstance(queue_size, int) or queue_size < 1:
            raise ConfigError(f"queue size must be a positive integer, got {queue_size!r}")
        self.key, self.poll_s = key, poll_s
        self.drops = DropCounter()
        self.received = 0
        self.ros_type: str | None = None
        self._wake = threading.Event()
        try:
            self._sub = session.declare_subscriber(key, zenoh.handlers.RingChannel(queue_size))
        except zenoh.ZError as exc:
            raise TransportError(f"cannot subscribe to {key!r}: {exc}") from exc

    def receive(self, timeout_s: float, stop_event: threading.Event | None = None) -> ReceivedFrame | None:
        """Return the oldest frame still in the ring, or None after timeout_s (or stop)."""
        sample = poll_ring(self._sub, self.key, timeout_s, stop_event or self._wake, self.poll_s)
        return None if sample is None else self._to_frame(sample)

    def _to_frame(self, sample: zenoh.Sample) -> ReceivedFrame:
        meta = FrameMeta()  # the bridge attaches nothing: unsequenced
        self.drops.update(meta)
        self.received += 1
        recv_ns, recv_mono = time.time_ns(), time.monotonic_ns()
        data = sample.payload.to_bytes()
        error, payload, encoding = None, data, "application/cdr"
        try:
            image, ros_type = decode_bridge_image(data)
            payload, encoding = image.payload, image.encoding
            self.ros_type = self.ros_type or ros_type
            if image.stamp_ns > 0:
                meta = FrameMeta(stamp_ns=image.stamp_ns)
        except FrameError as exc:
            error = exc
        return ReceivedFrame(payload=payload, encoding=encoding, key=str(sample.key_expr), meta=meta,
                             recv_ns=recv_ns, recv_mono_ns=recv_mono, error=error)

    def close(self) -> None:
        try:
            self._sub.undeclare()
        except zenoh.ZError:
            pass


class BridgeGraph:
    """The DDS publishers routed by the bridges in reach, from their liveliness tokens (kept while
    they live), as TopicPublishers named relative to the run's bridge namespace: a key under it is
    a topic of ``home_of(namespace)``, any other key the topic ``/<key>`` of a bridge without one."""

    def __init__(self, session: zenoh.Session, namespace: str) -> None:
        self.prefix = namespace.strip("/")
        self.home = home_of(namespace)
        self._lock = threading.Lock()
        self._pubs: dict[str, TopicPublisher] = {}
        try:
            self._sub = session.liveliness().declare_subscriber(PUBLISHER_TOKENS, self._on_token, history=True)
        except zenoh.ZError as exc:
            raise TransportError(f"cannot watch the bridge's ROS 2 graph: {exc}") from exc

    def _on_token(self, sample: zenoh.Sample) -> None:
        # A Zenoh thread: a malformed token is ignored, never raised.
        token = str(sample.key_expr)
        parts = token.split("/")
        if len(parts) < 7 or parts[3] != "MP":
            return
        key, ros_type = parts[4].replace(SLASH, "/").strip("/"), parts[5].replace(SLASH, "/")
        if self.prefix and key.startswith(self.prefix + "/"):
            pub = TopicPublisher("/" + key[len(self.prefix) + 1:], ros_type, self.home)
        else:
            pub = TopicPublisher("/" + key, ros_type, self.home if not self.prefix else home_of("/"))
        with self._lock:
            if sample.kind == zenoh.SampleKind.DELETE:
                self._pubs.pop(token, None)
            elif token in self._pubs or len(self._pubs) < MAX_GRAPH_TOKENS:
                self._pubs[token] = pub

    def publishers(self) -> list[TopicPublisher]:
        with self._lock:
            return list(self._pubs.values())

    def close(self) -> None:
        try:
            self._sub.undeclare()
        except zenoh.ZError:
            pass


class BridgeResultPublisher:
    """ResultPublisher's interface, for a run through zenoh-bridge-ros2dds: the JSON results and
    stats on their plain keys (as without ROS), and also as std_msgs/String CDR and the stats as a
    diagnostic_msgs/DiagnosticArray on the bridge's keys of the result, stats and /diagnostics
    topics, for the DDS subscribers behind it. ``status_source``: set by the node (see
    RosResultPublisher); ``graph``: the bridges' publishers (BridgeGraph)."""

    def __init__(self, session: zenoh.Session, result_key: str, options: RosOptions) -> None:
        from aefabmap_runtime.adapters.zenoh_transport import ResultPublisher

        if options.bridge is None:
            raise ConfigError("a bridge result publisher needs the bridge's namespace")
        self.options = options
        self.status_source: Callable[[], object] | None = None
        self.hardware_id = socket.gethostname()
        self._previous_stats: dict | None = None
        self._pubs: list = []
        self.plain = self.graph = None
        try:
            self.plain = ResultPublisher(session, result_key)
            self.graph = BridgeGraph(session, options.bridge)
            self.results_pub, self.stats_pub, self.diagnostics_pub = (
                self._declare(session, bridge_key(options.bridge, options.resolve(topic)))
                for topic in (options.result_topic, options.stats_topic, DIAGNOSTICS_TOPIC))
        except BaseException:
            self.close()
            raise
        self.result_key, self.stats_key = self.plain.result_key, self.plain.stats_key

    def _declare(self, session: zenoh.Session, key: str):
        try:
            pub = session.declare_publisher(key, congestion_control=zenoh.CongestionControl.DROP)
        except zenoh.ZError as exc:
            raise TransportError(f"cannot publish on {key!r}: {exc}") from exc
        self._pubs.append(pub)
        return pub

    def _put(self, pub, payload: bytes) -> None:
        try:
            pub.put(payload)
        except zenoh.ZError as exc:
            raise TransportError(f"cannot publish on {pub.key_expr}: {exc}") from exc

    def publish_result(self, result: dict | bytes) -> None:
        self.plain.publish_result(result)
        self._put(self.results_pub, encode_string_cdr(json_text(result)))

    def publish_stats(self, stats: dict | bytes) -> bytes:
        """Publish the stats; returns the DiagnosticArray CDR sent (the ros2-profile log records it)."""
        self.plain.publish_stats(stats)
        self._put(self.stats_pub, encode_string_cdr(json_text(stats)))
        diagnostics = self._diagnostics(stats)
        self._put(self.diagnostics_pub, diagnostics)
        return diagnostics

    def _diagnostics(self, stats: dict | bytes) -> bytes:
        o = self.options
        cdr, self._previous_stats = diagnostics_cdr(stats, self.status_source, self._previous_stats,
                                                    name=f"aefabmap: {o.node}", hardware_id=self.hardware_id,
                                                    node=o.fq_namespace.rstrip("/") + "/" + o.node)
        return cdr

    def warnings(self) -> list[str]:
        """Nothing to warn about results: the bridge gives them the DDS readers' type."""
        return []

    def close(self) -> None:
        for pub in self._pubs:
            try:
                pub.undeclare()
            except zenoh.ZError:
                pass
        self._pubs = []
        for part in (self.plain, self.graph):
            if part is not None:
                part.close()
