"""ROS 2 over Zenoh without a bridge: speak rmw_zenoh's wire format directly.

What rmw_zenoh (ros2/rmw_zenoh, docs/design.md and its sources) puts on the wire, and
what this module relies on:

- data key ``<domain>/<topic without leading slash>/<type, DDS-mangled>/<type hash>``, e.g.
  ``0/camera/image_raw/sensor_msgs::msg::dds_::Image_/RIHS01_<64 hex>``; Humble sends
  ``TypeHashNotSupported`` as the hash, so the subscriber takes any hash (``*``);
- payload: the message in CDR (runtime/aefabmap_runtime/adapters/ros_cdr.py);
- attachment (zenoh-ext serialization): int64 sequence number, int64 source timestamp
  (ns), then the publisher gid as a sequence (LEB128 length, then the bytes), all
  little-endian. The gid is 16 bytes (rmw_zenoh's Humble port too, though Humble's
  ``RMW_GID_STORAGE_SIZE`` is 24: 24-byte gids are read as well), derived from the entity's
  liveliness token (see entity_gid). Older releases prefixed each field with its name as a string (``sequence_number``,
  ``source_timestamp``, ``source_gid``), some append the session id as a string; all are parsed;
- health: the stats also as diagnostic_msgs/DiagnosticArray on ``/diagnostics``;
- graph: liveliness tokens ``@ros2_lv/<domain>/<zid>/<nid>/<eid>/<kind>/<enclave>/<ns>/
  <node>[/<topic>/<type>/<hash>/<qos>]`` with kind ``NN`` (node), ``MP`` (publisher), ``MS``
  (subscription); names have ``/`` replaced by ``%``; the QoS chunk leaves out what equals
  rmw_zenoh's default (``::,:,:,:,,``: reliable, volatile, keep last 42); the image subscription
  says the sensor-data profile cameras publish with (``2::,<queue>:,:,:,,``: best effort).

The subscriber hands the node :class:`~zenoh_transport.ReceivedFrame` objects, like the
plain-Zenoh FrameSubscriber, so the node's loop does not care which one it runs: the CDR is
decoded here (a message that cannot be used carries its FrameError in ``error``), the frame
stamp is the header stamp (else the attachment's source timestamp), and drops are counted
from the sequence numbers per publisher gid.
"""

from __future__ import annotations

import logging
import socket
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import xxhash
import zenoh

from aefabmap_runtime.errors import ConfigError, TransportError
from aefabmap_runtime.adapters.frames import FrameError
from aefabmap_runtime.adapters.ros_cdr import (  # noqa: F401 - the RIHS01 names are this module's API too
    COMPRESSED_IMAGE_RIHS01,
    COMPRESSED_IMAGE_TYPE,
    DIAGNOSTIC_ARRAY_RIHS01,
    IMAGE_RIHS01,
    RIHS01_OF,
    STRING_RIHS01,
    DECODERS,
    DIAGNOSTIC_ARRAY_TYPE,
    IMAGE_TYPE,
    STRING_TYPE,
    DiagnosticStatus,
    encode_diagnostic_array_cdr,
    encode_string_cdr,
)
from aefabmap_runtime.adapters.ros_diagnostics import (  # noqa: F401 - re-exported for the ROS adapters
    DIAG_ERROR,
    DIAG_OK,
    DIAG_WARN,
    DIAGNOSTICS_TOPIC,
    diagnostic_level,
    diagnostic_values,
    diagnostics_cdr,
    json_text,
    node_diagnostic,
)
from aefabmap_runtime.adapters.zenoh_transport import (
    DropCounter,
    FrameMeta,
    ReceivedFrame,
    poll_ring,
    result_key_for,
)
from aefabmap_runtime.core.kernels.varint import read_varint

ADMIN_SPACE = "@ros2_lv"
#: Hash chunk of Humble, which has no type hashes.
HUMBLE_TYPE_HASH = "TypeHashNotSupported"
#: rmw's QoS policy values (rmw/types.h), as rmw_zenoh writes them in a liveliness token.
RELIABLE, BEST_EFFORT = 1, 2
TRANSIENT_LOCAL, VOLATILE = 1, 2
KEEP_LAST, KEEP_ALL = 1, 2
#: rmw_zenoh's default QoS (its qos.cpp): a token leaves a field empty when it has this value.
RMW_ZENOH_DEFAULT_QOS = (RELIABLE, VOLATILE, KEEP_LAST, 42)
#: QoS chunk of a liveliness token whose QoS is rmw_zenoh's default (reliable, volatile, keep last 42;
#: deadline, lifespan and liveliness lease infinite, liveliness automatic).
DEFAULT_QOS_CHUNK = "::,:,:,:,,"
GID_BYTES = 16
#: Where a ROS 2 run's session listens by default: as rmw_zenoh's nodes do (its default session
#: config: a peer that connects to the router and listens on loopback), so the camera node on this
#: host, told of this one by the router's gossip, sends its images directly.
ROS_PEER_LISTEN = "tcp/127.0.0.1:0"
#: The gid length rmw_zenoh puts in the attachment, per distribution: 16 everywhere (Humble's
#: RMW_GID_STORAGE_SIZE is 24, but rmw_zenoh's Humble port hard-codes 16, ros2/rmw_zenoh#388).
GID_STORAGE_BYTES = {"humble": 16, "jazzy": 16}
#: Gid lengths accepted in a received attachment (24: Humble's RMW_GID_STORAGE_SIZE, other sources).
RECEIVED_GID_BYTES = (16, 24)
#: ``auto``: the distribution the camera's samples carry (their key's type-hash chunk).
DISTROS = ("auto", "humble", "jazzy")
#: Result and stats topics, relative: resolved in the node's namespace (``/lcd/result`` in ``/``).
RESULT_TOPIC = "lcd/result"
STATS_TOPIC = "lcd/stats"
#: Publishers (and subscriptions) of the graph kept at most: a peer declaring tokens without end
#: cannot grow the node's memory without bound.
MAX_GRAPH_TOKENS = 10_000
log = logging.getLogger("aefabmap.ros")
_INT64_MAX = 2**63 - 1


def distro_of_key(key: str) -> str | None:
    """The distribution a data key's type-hash chunk (its last) says: ``humble`` for
    TypeHashNotSupported, ``jazzy`` for an RIHS01 hash (Iron and later), None otherwise."""
    chunk = key.rsplit("/", 1)[-1]
    if chunk == HUMBLE_TYPE_HASH:
        return "humble"
    return "jazzy" if chunk.startswith("RIHS01_") else None


def mangle_type(ros_type: str) -> str:
    """``sensor_msgs/msg/Image`` -> ``sensor_msgs::msg::dds_::Image_`` (rmw's DDS type name)."""
    parts = ros_type.split("/")
    if len(parts) != 3 or not all(parts):
        raise ConfigError(f"ROS type must look like pkg/msg/Name, got {ros_type!r}")
    return f"{parts[0]}::{parts[1]}::dds_::{parts[2]}_"


def check_topic(topic: str) -> str:
    """A fully qualified ROS topic name (``/camera/image_raw``), returned without the leading slash."""
    name = (topic or "").strip()
    if not name.startswith("/"):
        name = "/" + name
    body = name.strip("/")
    if not body or any(not part or not all(c.isalnum() or c == "_" for c in part) for part in body.split("/")):
        raise ConfigError(f"ROS topic must be a name such as /camera/image_raw, got {topic!r}")
    return body


def check_domain(domain: int) -> int:
    if not isinstance(domain, int) or isinstance(domain, bool) or not 0 <= domain <= 232:
        raise ConfigError(f"ROS domain id must be an integer in 0..232, got {domain!r}")
    return domain


def domain_from_env(environ) -> int:
    """The domain id ROS 2 tools use: ROS_DOMAIN_ID when set (ConfigError unless an integer in
    0..232), else 0."""
    text = environ.get("ROS_DOMAIN_ID", "").strip()
    if not text:
        return 0
    if not text.isdigit():
        raise ConfigError(f"ROS_DOMAIN_ID must be an integer in 0..232, got {text[:20]!r}")
    return check_domain(int(text))


def data_key(domain: int, topic: str, ros_type: str, type_hash: str = "*") -> str:
    """rmw_zenoh's data key of a topic (``type_hash="*"``: any distribution's hash)."""
    return f"{check_domain(domain)}/{check_topic(topic)}/{mangle_type(ros_type)}/{type_hash}"


def image_key(domain: int, topic: str) -> str:
    """Subscription key for both image types of a topic: ``<domain>/<topic>/*/*``.

    The type chunk is checked per sample (Image_ or CompressedImage_, anything else is
    counted as ``wrong_encoding``).
    """
    return f"{check_domain(domain)}/{check_topic(topic)}/*/*"


def bridge_key(namespace: str, topic: str) -> str:
    """The bridge's key of a ROS topic: ``camera/image_raw``, or ``bot1/camera/image_raw`` behind a
    bridge given the namespace ``/bot1`` (zenoh-bridge-ros2dds, ros2dds_bridge.py). ConfigError for a name
    that is not a ROS name."""
    prefix = namespace.strip("/")
    if prefix:
        check_topic(prefix)
    return f"{prefix}/{check_topic(topic)}" if prefix else check_topic(topic)


def _mangle_name(name: str) -> str:
    return name.replace("/", "%") or "%"


def qos_chunk(reliability: int = RELIABLE, durability: int = VOLATILE, history: int = KEEP_LAST,
              depth: int = 42) -> str:
    """The QoS chunk of a liveliness token as rmw_zenoh writes it (liveliness_utils.cpp,
    qos_to_keyexpr): ``<reliability>:<durability>:<history>,<depth>:<deadline s>,<ns>:<lifespan s>,<ns>:
    <liveliness>,<lease s>,<ns>``, each field empty when it holds rmw_zenoh's default (deadline,
    lifespan and lease are always the default here)."""
    fields = (reliability, durability, history, depth)
    r, d, h, n = ("" if value == default else str(value) for value, default in zip(fields, RMW_ZENOH_DEFAULT_QOS))
    return f"{r}:{d}:{h},{n}:,:,:,,"


def sensor_data_qos(depth: int) -> str:
    """QoS chunk of a subscription with ROS 2's sensor-data profile (best effort, volatile, keep
    last ``depth``): what camera drivers publish with, so tools that compare QoS see a match."""
    return qos_chunk(BEST_EFFORT, VOLATILE, KEEP_LAST, depth)


def liveliness_token(domain: int, zid: str, node_id: int, entity_id: int, kind: str, node: str,
                     topic: str | None = None, ros_type: str | None = None, type_hash: str | None = None,
                     namespace: str = "/", enclave: str = "/", qos: str = DEFAULT_QOS_CHUNK) -> str:
    """The liveliness key expression rmw_zenoh declares for a node (NN) or a topic endpoint (MP/MS)."""
    parts = [ADMIN_SPACE, str(check_domain(domain)), zid, str(node_id), str(entity_id), kind,
             _mangle_name(enclave), _mangle_name(namespace), _mangle_name(node)]
    if topic is not None:
        parts += [_mangle_name("/" + check_topic(topic)), mangle_type(ros_type or ""), type_hash or HUMBLE_TYPE_HASH,
                  qos]
    return "/".join(parts)


# --------------------------------------------------------------------------- gids
# rmw_zenoh derives an entity's gid from its liveliness token: XXH3-128 (seed 0, default
# secret) of the token's text, stored as the low 64 bits then the high 64 bits, each
# little-endian (liveliness_utils.cpp, Entity's constructor).


def entity_gid(token: str, size: int = GID_BYTES) -> bytes:
    """The gid rmw_zenoh gives the entity of a liveliness token: XXH3-128 of the token, low 64
    bits then high 64 bits, little-endian; zero-padded to ``size`` bytes (16 or 24)."""
    return xxhash.xxh3_128_intdigest(token.encode()).to_bytes(16, "little").ljust(size, b"\x00")


# --------------------------------------------------------------------------- attachment


@dataclass(frozen=True)
class RmwAttachment:
    """rmw_zenoh's per-sample attachment: sequence number, source timestamp (ns), gid (16 or 24 bytes)."""

    sequence_number: int
    source_timestamp: int
    gid: bytes

    def to_bytes(self) -> bytes:
        return struct.pack("<qqB", self.sequence_number, self.source_timestamp, len(self.gid)) + self.gid


def parse_attachment(data: bytes) -> RmwAttachment:
    """Parse an rmw_zenoh attachment (current, keyed or with a trailing session id);
    ValueError when malformed."""
    if len(data) > 256:
        raise ValueError(f"attachment of {len(data)} bytes is not rmw_zenoh's")
    pos, fields = 0, []
    keyed = data[:1] == b"\x0f" and data[1:16] == b"sequence_number"
    for name, kind in (("sequence_number", "q"), ("source_timestamp", "q"), ("source_gid", "gid")):
        if keyed:
            n, pos = read_varint(data, pos)
            if data[pos : pos + n] != name.encode():
                raise ValueError(f"attachment field {name} missing")
            pos += n
        if kind == "q":
            if pos + 8 > len(data):
                raise ValueError(f"attachment too short for {name}")
            fields.append(struct.unpack_from("<q", data, pos)[0])
            pos += 8
        else:
            n, pos = read_varint(data, pos)
            if n not in RECEIVED_GID_BYTES or pos + n > len(data):
                raise ValueError(f"attachment gid of {n} bytes (expected 16 or 24)")
            fields.append(bytes(data[pos : pos + n]))
            pos += n
    if pos < len(data):  # a trailing session id string, in some releases
        n, after = read_varint(data, pos)
        if after + n != len(data):
            raise ValueError(f"{len(data) - pos} unexpected bytes after the attachment gid")
    return RmwAttachment(*fields)


def meta_from_attachment(data: bytes | None) -> FrameMeta:
    """FrameMeta (seq, source stamp, src = gid hex) of an rmw_zenoh attachment; never raises."""
    if not data:
        return FrameMeta(problem="no rmw_zenoh attachment")
    try:
        att = parse_attachment(data)
    except ValueError as exc:
        return FrameMeta(problem=f"rmw_zenoh attachment: {exc}")
    problems = []
    seq = att.sequence_number if att.sequence_number >= 0 else None
    if seq is None:
        problems.append(f"sequence number {att.sequence_number} is negative")
    stamp = att.source_timestamp if att.source_timestamp > 0 else None
    return FrameMeta(seq=seq, stamp_ns=stamp, src=att.gid.hex(), problem="; ".join(problems))


# --------------------------------------------------------------------------- subscriber


class RosFrameSubscriber:
    """Subscribes to a ROS 2 image topic's rmw_zenoh keys; same interface as FrameSubscriber.

    ``receive`` returns a ReceivedFrame whose payload/encoding follow the frames contract
    (decoded from CDR here) and whose ``error`` is the FrameError of a message that could
    not be used (the node counts it). ``meta.stamp_ns`` is the header stamp, else the
    attachment's source timestamp; ``meta.src`` the publisher gid (drops are per gid).
    """

    def __init__(self, session: zenoh.Session, domain: int, topic: str, *, queue_size: int = 2,
                 poll_s: float = 0.002) -> None:
        if not isinstance(queue_size, int) or queue_size < 1:
            raise ConfigError(f"queue size must be a positive integer, got {queue_size!r}")
        self.key = image_key(domain, topic)
        self.poll_s = poll_s
        self.drops = DropCounter()
        self.received = 0
        self.ignored = 0
        self.bad_attachments = 0
        self.last_bad_attachment = ""
        self.distro: str | None = None  # the first image sample's, see distro_of_key
        self.ros_type: str | None = None  # and its message type (Image or CompressedImage)
        self._types = {mangle_type(t): t for t in (IMAGE_TYPE, COMPRESSED_IMAGE_TYPE)}
        self._wake = threading.Event()
        try:
            self._sub = session.declare_subscriber(self.key, zenoh.handlers.RingChannel(queue_size))
        except zenoh.ZError as exc:
            raise TransportError(f"cannot subscribe to {self.key!r}: {exc}") from exc

    def receive(self, timeout_s: float, stop_event: threading.Event | None = None) -> ReceivedFrame | None:
        """Return the oldest frame still in the ring, or None after timeout_s (or stop)."""
        sample = poll_ring(self._sub, self.key, timeout_s, stop_event or self._wake, self.poll_s)
        return None if sample is None else self._to_frame(sample)

    def _to_frame(self, sample: zenoh.Sample) -> ReceivedFrame:
        key = str(sample.key_expr)
        att = sample.attachment
        meta = meta_from_attachment(att.to_bytes() if att is not None else None)
        if meta.problem:
            self.bad_attachments += 1
            self.last_bad_attachment = meta.problem
        self.drops.update(meta)
        self.received += 1
        recv_ns, recv_mono = time.time_ns(), time.monotonic_ns()
        data = sample.payload.to_bytes()
        ros_type = self._types.get(key.split("/")[-2])
        error, payload, encoding = None, data, "application/cdr"
        if ros_type is None:
            error = FrameError("wrong_encoding", f"{key}: not a sensor_msgs Image or CompressedImage")
        else:
            if self.distro is None:
                self.distro, self.ros_type = distro_of_key(key), ros_type
            try:
                image = DECODERS[ros_type](data)
                payload, encoding = image.payload, image.encoding
                if image.stamp_ns > 0:
                    meta = FrameMeta(seq=meta.seq, stamp_ns=image.stamp_ns, src=meta.src, problem=meta.problem)
            except FrameError as exc:
                error = exc
        return ReceivedFrame(payload=payload, encoding=encoding, key=key, meta=meta, recv_ns=recv_ns,
                             recv_mono_ns=recv_mono, error=error)

    def close(self) -> None:
        try:
            self._sub.undeclare()
        except zenoh.ZError:
            pass


# --------------------------------------------------------------------------- publisher


class RosPublisher:
    """A ROS 2 publisher of one message type on rmw_zenoh's key, with its attachment and its
    liveliness token (so ``ros2 topic list`` shows the topic); ``put_cdr`` sends a CDR message."""

    def __init__(self, session: zenoh.Session, domain: int, topic: str, type_hash: str, zid: str,
                 node_id: int, entity_id: int, node: str, gid_bytes: int = GID_BYTES, namespace: str = "/",
                 ros_type: str = STRING_TYPE) -> None:
        self.key = data_key(domain, topic, ros_type, type_hash)
        self.topic, self.ros_type, self.type_hash = "/" + check_topic(topic), ros_type, type_hash
        self.token = liveliness_token(domain, zid, node_id, entity_id, "MP", node, topic, ros_type, type_hash,
                                      namespace=namespace)
        self.gid = entity_gid(self.token, gid_bytes)
        self.seq = 0
        try:
            self._pub = session.declare_publisher(self.key, congestion_control=zenoh.CongestionControl.DROP)
            self._token = session.liveliness().declare_token(self.token)
        except zenoh.ZError as exc:
            raise TransportError(f"cannot declare ROS publisher on {self.key!r}: {exc}") from exc

    def put_cdr(self, payload: bytes) -> None:
        self.seq += 1  # rmw_zenoh numbers messages from 1
        att = RmwAttachment(self.seq, min(time.time_ns(), _INT64_MAX), self.gid).to_bytes()
        try:
            self._pub.put(payload, attachment=att)
        except zenoh.ZError as exc:
            raise TransportError(f"cannot publish on {self.key!r}: {exc}") from exc

    def close(self) -> None:
        for entity in (self._token, self._pub):
            try:
                entity.undeclare()
            except zenoh.ZError:
                pass


class RosStringPublisher(RosPublisher):
    """A ROS 2 ``std_msgs/msg/String`` publisher (see RosPublisher)."""

    def put(self, text: str) -> None:
        self.put_cdr(encode_string_cdr(text))


@dataclass(frozen=True)
class RosOptions:
    """The ROS 2 side of a run: image topic, domain id, node name, and the distribution whose
    type hash the result topics carry (``humble``: TypeHashNotSupported; ``jazzy``: RIHS01,
    also Iron, Kilted and Rolling; ``auto``, the default: the camera's, from its first image
    sample, the ROS result topics being declared then).

    bridge: None to speak rmw_zenoh; else the namespace zenoh-bridge-ros2dds was given (``/``:
    none) to read the topic through that bridge's keys instead (ros2dds_bridge.py: no domain,
    node or type hash there)."""

    topic: str
    domain: int = 0
    node: str = "aefabmap"
    distro: str = "auto"
    namespace: str = "/"
    result_topic: str = RESULT_TOPIC
    stats_topic: str = STATS_TOPIC
    bridge: str | None = None

    def __post_init__(self) -> None:
        check_topic(self.topic)
        check_domain(self.domain)
        if "/" in self.node.strip("/") or self.node.startswith("/"):
            raise ConfigError(f"ROS node name must be a plain name such as aefabmap, got {self.node!r}")
        check_topic(self.node)
        if self.namespace.strip("/"):
            check_topic(self.namespace)
        elif self.namespace != "/":
            raise ConfigError(f"ROS namespace must be / or a name such as /robot1, got {self.namespace!r}")
        check_topic(self.result_topic)
        check_topic(self.stats_topic)
        if self.distro not in DISTROS:
            raise ConfigError(f"ROS distribution must be one of {DISTROS}, got {self.distro!r}")
        if self.bridge is not None:
            if self.bridge.strip("/"):
                check_topic(self.bridge)
            elif self.bridge != "/":
                raise ConfigError(f"bridge namespace must be / or a name such as /bot1, got {self.bridge!r}")
            if self.distro != "auto":
                raise ConfigError("a ROS distribution means nothing through zenoh-bridge-ros2dds: its keys carry "
                                  "no type hash")

    @property
    def image_key(self) -> str:
        """The key the images arrive on: rmw_zenoh's (any type, any hash), or the bridge's."""
        if self.bridge is not None:
            return bridge_key(self.bridge, self.topic)
        return image_key(self.domain, self.topic)

    @property
    def default_results_key(self) -> str:
        """Plain-Zenoh JSON results key: the ``lcd`` sibling of the topic (``camera/lcd``; through a
        bridge with a namespace, of its key: ``bot1/camera/lcd``)."""
        return result_key_for(self.image_key if self.bridge is not None else check_topic(self.topic))

    def resolve(self, name: str) -> str:
        """A topic name as ROS resolves it in this node's namespace: absolute names stay, relative
        ones (``lcd/result``) go under the namespace (``/robot1/lcd/result``)."""
        if name.startswith("/"):
            return "/" + check_topic(name)
        ns = self.namespace.strip("/")
        return "/" + (f"{ns}/" if ns else "") + check_topic(name)

    @property
    def fq_namespace(self) -> str:
        """The namespace as a fully qualified name (``/`` or ``/robot1``)."""
        return "/" + self.namespace.strip("/")

    @property
    def fq_topic(self) -> str:
        """The image topic as a fully qualified name (``/camera/image_raw``)."""
        return "/" + check_topic(self.topic)

    def to_dict(self) -> dict:
        """The log metadata's ``ros`` (through a bridge: no domain, no distribution; its namespace)."""
        bridged = self.bridge is not None
        return {"topic": self.topic, "domain": None if bridged else self.domain, "node": self.node,
                "distro": None if bridged else self.distro,
                "namespace": self.fq_namespace, "result_topic": self.resolve(self.result_topic),
                "stats_topic": self.resolve(self.stats_topic),
                **({"bridge": self.bridge} if self.bridge is not None else {})}


class RosGraph:
    """This run's presence in the ROS 2 graph: the node token, and the image subscription token
    once the distribution is known (its type hash is part of the token)."""

    def __init__(self, session: zenoh.Session, options: RosOptions) -> None:
        self.session = session
        self.zid = str(session.info.zid())
        self.options = options
        self._tokens = [self._declare(liveliness_token(options.domain, self.zid, 0, 0, "NN", options.node,
                                                       namespace=options.fq_namespace))]

    def _declare(self, token: str):
        try:
            return self.session.liveliness().declare_token(token)
        except zenoh.ZError as exc:
            raise TransportError(f"cannot declare ROS liveliness tokens: {exc}") from exc

    def declare_subscription(self, distro: str, ros_type: str | None = None, depth: int = 2) -> None:
        """The image subscription token, of the camera's message type when known (else
        sensor_msgs/msg/Image; the subscription takes CompressedImage too), so the graph lists
        one type on the camera topic. Its QoS is the sensor-data profile cameras publish with
        (best effort, volatile), keep last ``depth`` (the frame queue)."""
        o = self.options
        ros_type = ros_type or IMAGE_TYPE
        type_hash = HUMBLE_TYPE_HASH if distro == "humble" else RIHS01_OF[ros_type]
        self._tokens.append(self._declare(
            liveliness_token(o.domain, self.zid, 0, 1, "MS", o.node, o.topic, ros_type, type_hash,
                             namespace=o.fq_namespace, qos=sensor_data_qos(depth))))

    def close(self) -> None:
        for token in self._tokens:
            try:
                token.undeclare()
            except zenoh.ZError:
                pass


class RosResultPublisher:
    """ResultPublisher's interface, for a ROS 2 run: the JSON results and stats on their
    plain Zenoh keys (as without ROS), and also as std_msgs/String on ``/lcd/result`` and
    ``/lcd/stats`` and as diagnostic_msgs/DiagnosticArray on ``/diagnostics`` for ROS 2 nodes,
    with the type hash of the run's distribution.

    wire_distro: with distribution ``auto``, returns the camera's (distribution, message type)
    once known (the frame subscriber's ``distro`` and ``ros_type``); the ROS topics and the
    subscription token are declared then, and only the plain keys carry what is published before.
    status_source: set by the node, returns its StatusMessage (places, map size and per-stage
    times for the diagnostics). ``warnings()``: why results may reach no ROS subscriber now
    (each also logged once). subscription_depth: the frame queue, advertised as the image
    subscription's history depth. ``watch``: the domain's graph (GraphWatch).
    """

    def __init__(self, session: zenoh.Session, result_key: str, options: RosOptions,
                 wire_distro: Callable[[], tuple[str | None, str | None]] | None = None,
                 subscription_depth: int = 2) -> None:
        from aefabmap_runtime.adapters.zenoh_transport import ResultPublisher

        self.session, self.options, self.wire_distro = session, options, wire_distro
        self.subscription_depth = subscription_depth
        self.distro: str | None = None
        self.ros_results = self.ros_stats = self.ros_diagnostics = None
        self.status_source: Callable[[], object] | None = None
        self.hardware_id = socket.gethostname()
        self._previous_stats: dict | None = None
        self._results_sent = 0
        self.graph = RosGraph(session, options)
        try:
            self.plain = ResultPublisher(session, result_key)
            self.watch = GraphWatch(session, options.domain)
        except BaseException:
            self.close()
            raise
        self.result_key, self.stats_key = self.plain.result_key, self.plain.stats_key
        self._logged: set[str] = set()
        if options.distro != "auto":
            self._adopt(options.distro)

    def _adopt(self, distro: str, camera_type: str | None = None) -> None:
        o = self.options
        gid_bytes = GID_STORAGE_BYTES[distro]

        def publisher(topic: str, entity_id: int, ros_type: str, cls=RosPublisher):
            type_hash = HUMBLE_TYPE_HASH if distro == "humble" else RIHS01_OF[ros_type]
            return cls(self.session, o.domain, o.resolve(topic), type_hash, self.graph.zid, 0, entity_id, o.node,
                       gid_bytes, o.fq_namespace, ros_type)

        try:
            self.graph.declare_subscription(distro, camera_type, self.subscription_depth)
            self.ros_results = publisher(o.result_topic, 2, STRING_TYPE, RosStringPublisher)
            self.ros_stats = publisher(o.stats_topic, 3, STRING_TYPE, RosStringPublisher)
            self.ros_diagnostics = publisher(DIAGNOSTICS_TOPIC, 4, DIAGNOSTIC_ARRAY_TYPE)
        except BaseException:
            self.close()
            raise
        self.distro = distro

    def _ready(self) -> bool:
        if self.distro is None and self.wire_distro is not None:
            seen, camera_type = self.wire_distro()
            if seen is not None:
                self._adopt(seen, camera_type)
        return self.distro is not None

    def publish_result(self, result: dict | bytes) -> None:
        self.plain.publish_result(result)
        # Learn the distribution before counting the result: a status read from another thread in
        # between would otherwise warn that it is not learnt while the camera's sample has taught it.
        ready = self._ready()
        self._results_sent += 1
        if ready:
            self.ros_results.put(json_text(result))
        self._log_warnings()

    def publish_stats(self, stats: dict | bytes) -> bytes | None:
        """Publish the stats; returns the DiagnosticArray CDR sent on /diagnostics (None before the
        ROS topics are declared), which the run's ros2-profile log records as it went out."""
        self.plain.publish_stats(stats)
        diagnostics = None
        if self._ready():
            self.ros_stats.put(json_text(stats))
            diagnostics = self._diagnostics(stats)
            self.ros_diagnostics.put_cdr(diagnostics)
        self._log_warnings()
        return diagnostics

    def _diagnostics(self, stats: dict | bytes) -> bytes:
        """The stats (and the node's status, when given) as a DiagnosticArray in CDR."""
        o = self.options
        cdr, self._previous_stats = diagnostics_cdr(stats, self.status_source, self._previous_stats,
                                                    name=f"aefabmap: {o.node}", hardware_id=self.hardware_id,
                                                    node=_fq_node(o), distro=self.distro or "")
        return cdr

    def warnings(self) -> list[str]:
        """Why results published now may reach no ROS 2 subscriber (empty when none)."""
        out = []
        if self.distro is None and self._results_sent:
            out.append(f"--ros-distro auto has not learnt the ROS 2 distribution (no camera sample yet): results go "
                       f"to the Zenoh key {self.result_key} only, not to {self.options.resolve(self.options.result_topic)}")
        for pub in (self.ros_results, self.ros_stats, self.ros_diagnostics):
            if pub is not None:
                out += self.watch.mismatches(pub.topic, pub.ros_type, pub.type_hash)
        return out

    def _log_warnings(self) -> None:
        for text in self.warnings():
            if text not in self._logged:
                self._logged.add(text)
                log.warning("%s", text)

    def close(self) -> None:
        for pub in (self.ros_results, self.ros_stats, self.ros_diagnostics, getattr(self, "plain", None),
                    getattr(self, "watch", None)):
            if pub is not None:
                pub.close()
        self.ros_results = self.ros_stats = self.ros_diagnostics = None
        self.graph.close()


def _fq_node(options: RosOptions) -> str:
    return options.fq_namespace.rstrip("/") + "/" + options.node


@dataclass(frozen=True)
class TopicPublisher:
    """A publisher seen in a ROS 2 graph: its topic (``/camera/image_raw``), message type
    (``sensor_msgs/msg/Image``) and where (``domain 0``; through a bridge, ``bridge <zid>``)."""

    topic: str
    ros_type: str
    where: str


def demangle_type(mangled: str) -> str:
    """``sensor_msgs::msg::dds_::Image_`` -> ``sensor_msgs/msg/Image`` (the mangled text when it is not one)."""
    parts = mangled.split("::")
    if len(parts) == 4 and parts[2] == "dds_" and parts[3].endswith("_"):
        return f"{parts[0]}/{parts[1]}/{parts[3][:-1]}"
    return mangled


class GraphWatch:
    """The ROS 2 graph as rmw_zenoh's liveliness tokens tell it (kept while they live): the
    subscriptions of the run's domain, so a publisher can tell whether the subscribers of its topic
    use another type hash, and the publishers of every domain, so the node can tell which image
    topics exist when its own has no publisher."""

    def __init__(self, session: zenoh.Session, domain: int) -> None:
        self.domain = check_domain(domain)
        self._lock = threading.Lock()
        self._subs: dict[str, tuple[str, str, str]] = {}  # token -> (topic, mangled type, hash)
        self._pubs: dict[str, TopicPublisher] = {}  # token -> its publisher
        try:
            self._sub = session.liveliness().declare_subscriber(f"{ADMIN_SPACE}/**", self._on_token, history=True)
        except zenoh.ZError as exc:
            raise TransportError(f"cannot watch the ROS 2 graph: {exc}") from exc

    def _on_token(self, sample: zenoh.Sample) -> None:
        # A Zenoh thread: a malformed token is ignored, never raised.
        token = str(sample.key_expr)
        parts = token.split("/")
        if len(parts) < 13 or parts[5] not in ("MS", "MP") or not (parts[1].isascii() and parts[1].isdigit()):
            return
        topic, domain = "/" + parts[9].replace("%", "/").strip("/"), int(parts[1])
        with self._lock:
            if sample.kind == zenoh.SampleKind.DELETE:
                self._subs.pop(token, None)
                self._pubs.pop(token, None)
            elif parts[5] == "MP":
                if token in self._pubs or len(self._pubs) < MAX_GRAPH_TOKENS:
                    self._pubs[token] = TopicPublisher(topic, demangle_type(parts[10]), f"domain {domain}")
            elif domain == self.domain and (token in self._subs or len(self._subs) < MAX_GRAPH_TOKENS):
                self._subs[token] = (topic, parts[10], parts[11])

    def publishers(self) -> list[TopicPublisher]:
        """The publishers alive now, in every domain (their ``where`` names it)."""
        with self._lock:
            return list(self._pubs.values())

    def mismatches(self, topic: str, ros_type: str, type_hash: str) -> list[str]:
        """One line per other type hash the subscriptions of ``topic`` (type ros_type) use."""
        mangled = mangle_type(ros_type)
        with self._lock:
            theirs = [h for t, m, h in self._subs.values() if t == topic and m == mangled and h != type_hash]
        return [f"{theirs.count(h)} subscriber(s) of {topic} listen under type hash {h} "
                f"({distro_of_key(h) or 'unknown distribution'}), results go out under {type_hash} "
                f"({distro_of_key(type_hash)}): they receive nothing (set --ros-distro)" for h in sorted(set(theirs))]

    def close(self) -> None:
        try:
            self._sub.undeclare()
        except zenoh.ZError:
            pass


