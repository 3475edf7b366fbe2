"""MCAP logging of a run and reading logs back for replay.

Log layout written by :class:`McapLogWriter`:

============== ====================================== ===============================
topic          schema / encoding                       content
============== ====================================== ===============================
/camera/image  ``foxglove.CompressedImage`` (protobuf) every n-th processed frame (jpeg/png;
                                                       raw frames are stored as gray PNG)
/lcd/result    ``aefabmap.LcdResult`` (jsonschema/json) one per processed frame
/lcd/stats     ``aefabmap.LcdStats`` (jsonschema/json)  periodic run statistics
/lcd/annotations ``foxglove.ImageAnnotations`` (protobuf) with the live view only (``--foxglove``):
                                                       inlier points + a text line on /camera/image
/lcd/place_image ``foxglove.CompressedImage`` (protobuf) with the live view only: the matched
                                                       place's thumbnail (never replayed)
============== ====================================== ===============================

The topics are McapLogConfig's (defaults above). The JSON schemas and messages are those of
runtime/aefabmap_runtime/core/records/messages.py (schemas generated from the message records). Metadata record
``aefabmap.log`` holds ``format_version`` (MESSAGE_FORMAT_VERSION, "major.minor"), the
three topic names and ``extraction_version`` (features.EXTRACTION_VERSION of the build that wrote
the log: a replay by a build that extracts features otherwise says why its frames differ);
``aefabmap.manifest`` and ``aefabmap.run_config`` each hold one key ``json`` with the JSON text
of the bundle manifest / run configuration. All are written at open, so they survive a crash.
Message ``sequence`` = the frame's sequence number in the run (0-based count of processed
frames); image ``timestamp`` = the frame's capture stamp.

Crash safety: zstd chunks of ``chunk_size`` bytes (256 KiB by default) written through an
unbuffered file, and a forced chunk flush every ``flush_interval_s`` seconds: a SIGKILL
loses at most one chunk or ``flush_interval_s`` of data. :class:`McapLogReader` reads
such a file (no summary) sequentially up to its last complete record and reports
``truncated`` and ``messages_read``.

Profile ``ros2`` (McapLogConfig.profile, ``--mcap-profile ros2``): the same run as a file that
``ros2 bag play``/``info``, rosbags and Foxglove read, written as rosbag2 writes MCAP
(runtime/aefabmap_runtime/adapters/rosbag2_mcap.py): MCAP profile ``ros2``, schemas ``ros2msg``
(runtime/aefabmap_runtime/adapters/ros_cdr.py definitions), messages ``cdr`` serialised by
mcap-ros2-support, each channel with its ``offered_qos_profiles`` and ``topic_type_hash``, and at
the file's end the ``rosbag2`` metadata record (topics, message counts, start and duration):

========================= ======================================== ===============================
topic                     type                                     content
========================= ======================================== ===============================
/camera/image/compressed  ``sensor_msgs/msg/CompressedImage``      every n-th processed frame, header
                                                                   stamp = capture stamp, frame_id;
                                                                   format "jpeg"/"png" (raw frames as
                                                                   lossless gray PNG)
/lcd/result               ``std_msgs/msg/String``                  the result's JSON (with ``sequence``)
/lcd/stats                ``std_msgs/msg/String``                  the stats' JSON
/diagnostics              ``diagnostic_msgs/msg/DiagnosticArray``  one per stats message: what a ROS 2
                                                                   run published on /diagnostics, else
                                                                   the same status made from the stats
========================= ======================================== ===============================

The result and stats channels carry channel metadata ``aefabmap.message`` (the JSON schema
title) so the reader tells them apart from any other String topic; the ``aefabmap.*`` metadata
records are the same as in the default profile (ROS tools ignore them). The live view's protobuf
topics are not written in this profile (ROS readers refuse protobuf schemas).

The reader also takes ROS 2 bags (``sensor_msgs/msg/CompressedImage`` and
``sensor_msgs/msg/Image``, CDR via mcap-ros2-support) and reads both profiles of our logs.
"""

from __future__ import annotations

import io
import json
import os
import socket
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from mcap.records import Channel, Header, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer
from mcap_protobuf.schema import build_file_descriptor_set

from aefabmap_runtime.errors import ConfigError, ImageDecodeError, InputError, LogError
from aefabmap_runtime.adapters.durable_files import open_regular
from aefabmap_runtime.adapters.foxglove_view import PLACE_IMAGE_TOPIC, VIEW_PROTOBUF
from aefabmap_runtime.adapters.frames import (
    FrameError,
    classify_encoding,
    compressed_format_to_encoding,
    decode_frame,
    encode_frame,
    pack_raw_rows,
)
from aefabmap_runtime.adapters.ros_diagnostics import DIAGNOSTICS_TOPIC, node_diagnostic
from aefabmap_runtime.adapters.rosbag2_mcap import Rosbag2Channels, compressed_image, diagnostic_array, text
from aefabmap_runtime.adapters.ros_cdr import (
    COMPRESSED_IMAGE_TYPE,
    DIAGNOSTIC_ARRAY_TYPE,
    STRING_TYPE,
    decode_compressed_cdr,
    decode_string_cdr,
)
from aefabmap_runtime.core.features.features import EXTRACTION_VERSION
from aefabmap_runtime.core.records.messages import (
    MESSAGE_FORMAT_VERSION,
    FrameResult,
    StatsMessage,
    check_readable,
)

IMAGE_TOPIC = "/camera/image"
RESULT_TOPIC = "/lcd/result"
STATS_TOPIC = "/lcd/stats"
MANIFEST_METADATA = "aefabmap.manifest"
RUN_CONFIG_METADATA = "aefabmap.run_config"
LOG_METADATA = "aefabmap.log"
#: The log layout and its messages share one version (runtime/aefabmap_runtime/core/records/messages.py).
LOG_FORMAT_VERSION = MESSAGE_FORMAT_VERSION
#: JSON channels are recognised by their schema name, whatever their topic.
RESULT_SCHEMA_NAME = FrameResult.TITLE
STATS_SCHEMA_NAME = StatsMessage.TITLE

COMPRESSIONS = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}
#: Log layouts: ours (protobuf/JSON, the default) and one ROS 2 tools play (see module docstring).
PROFILES = ("aefabmap", "ros2")
#: The image topic of the ros2 profile when none is set: ROS names compressed images so.
ROS2_IMAGE_TOPIC = "/camera/image/compressed"
#: Channel metadata key naming the JSON message a ros2-profile String channel carries.
MESSAGE_KIND_KEY = "aefabmap.message"
#: DiagnosticStatus name of the diagnostics a ros2-profile log makes from the stats of a run that
#: published none (no ROS 2 publisher: plain Zenoh, replay).
STATS_DIAGNOSTIC_NAME = "aefabmap"
#: Topics aefabmap writes that the reader does not read (the live view's, /diagnostics): a log's
#: other unread topics are listed in ReadStatus.unknown_topics.
OWN_UNREAD_TOPICS = frozenset((*VIEW_PROTOBUF, DIAGNOSTICS_TOPIC))
#: Unknown topics named in ReadStatus.describe (all of them are in to_dict).
MAX_DESCRIBED_TOPICS = 10


@dataclass(frozen=True)
class McapLogConfig:
    """Settings of the MCAP writer.

    chunk_size: bytes of uncompressed messages per chunk (smaller = less lost on a crash).
    compression: "zstd", "lz4" or "none".
    flush_interval_s: force out the chunk in progress at least this often (seconds).
    image_every: log every n-th processed frame's image (1 = all; needed for an exact replay).
    profile: "aefabmap" (protobuf/JSON) or "ros2" (CDR, read by ROS 2 tools); with "ros2" the
    default image topic becomes ROS2_IMAGE_TOPIC.
    """

    chunk_size: int = 256 * 1024
    compression: str = "zstd"
    flush_interval_s: float = 2.0
    image_every: int = 1
    image_topic: str = IMAGE_TOPIC
    result_topic: str = RESULT_TOPIC
    stats_topic: str = STATS_TOPIC
    frame_id: str = "camera"
    profile: str = "aefabmap"

    def __post_init__(self) -> None:
        if self.profile not in PROFILES:
            raise ConfigError(f"MCAP profile must be one of {list(PROFILES)}, got {self.profile!r}")
        if self.profile == "ros2" and self.image_topic == IMAGE_TOPIC:
            object.__setattr__(self, "image_topic", ROS2_IMAGE_TOPIC)  # frozen: set once, at construction
        if self.compression not in COMPRESSIONS:
            raise ConfigError(f"MCAP compression must be one of {sorted(COMPRESSIONS)}, got {self.compression!r}")
        if not isinstance(self.chunk_size, int) or self.chunk_size < 1024:
            raise ConfigError(f"MCAP chunk size must be an integer >= 1024 bytes, got {self.chunk_size!r}")
        if not isinstance(self.image_every, int) or self.image_every < 0:
            raise ConfigError(f"image_every must be an integer >= 0 (0 = no images), got {self.image_every!r}")
        if self.flush_interval_s <= 0:
            raise ConfigError(f"flush_interval_s must be > 0, got {self.flush_interval_s!r}")


class _UnbufferedFile:
    """Write-through file: every write reaches the OS at once (a SIGKILL loses nothing written)."""

    def __init__(self, path: Path, *, exclusive: bool = False) -> None:
        # exclusive: create or fail (FileExistsError), never truncate an existing file.
        self._f = open(path, "xb" if exclusive else "wb", buffering=0)  # noqa: SIM115 - closed in close()
        self._pos = 0

    def write(self, data) -> int:
        view = memoryview(data).cast("B")
        done = 0
        while done < len(view):
            done += self._f.write(view[done:])
        self._pos += done
        return done

    def tell(self) -> int:
        return self._pos

    def flush(self) -> None:
        pass

    def close(self) -> None:
        self._f.close()


#: MCAP stores times as unsigned 64-bit ns; protobuf timestamps are signed 64-bit.
_MAX_TIME_NS = 2**63 - 1


def _checked_time_ns(value, what: str) -> int:
    """``value`` as an int in [0, 2**63) ns, else LogError: refused before any byte of the
    message reaches the chunk (an out-of-range time used to abort the writer mid-chunk)."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not 0 <= int(value) <= _MAX_TIME_NS:
        text = repr(value)
        raise LogError(f"{what} time must be an integer number of ns in [0, 2**63), got {text[:40]}")
    return int(value)


def _json_bytes(doc: dict) -> bytes:
    return json.dumps(doc, separators=(",", ":"), allow_nan=True).encode()


def check_log_version(path: Path | str, log_meta: dict) -> tuple[int, int]:
    """(major, minor) of a log's format from its ``aefabmap.log`` metadata; LogError when
    this code cannot read it (a newer major version, or a malformed one)."""
    try:
        return check_readable(log_meta.get("format_version", "1"))
    except InputError as exc:
        raise LogError(f"cannot read MCAP log {path}: {exc}") from exc


class McapLogWriter:
    """Context manager writing one run to an MCAP file (see module docstring for the layout).

    path: output file (parent directory must exist and be writable).
    manifest / run_config: JSON-able dicts stored as metadata at open.
    extra_metadata: further metadata records (name -> JSON-able dict) written at open.
    exclusive: refuse an existing ``path`` (LogError caused by FileExistsError) instead of
    truncating it; the node's logs are opened so (runtime/aefabmap_runtime/adapters/rotating_log.py).
    Raises LogError (naming the path) when the file cannot be created or written.
    """

    def __init__(
        self,
        path: str | Path,
        config: McapLogConfig | None = None,
        *,
        manifest: dict | None = None,
        run_config: dict | None = None,
        extra_metadata: dict[str, dict] | None = None,
        exclusive: bool = False,
    ) -> None:
        self.path = Path(path)
        self.config = config or McapLogConfig()
        self.images_written = 0
        self.images_seen = 0
        self.messages_written = 0
        self._closed = False
        self._ros2 = self.config.profile == "ros2"
        self._ros: Rosbag2Channels | None = None
        self._previous_stats: dict | None = None  # for the level of diagnostics made from stats
        try:
            self._file = _UnbufferedFile(self.path, exclusive=exclusive)
        except OSError as exc:
            raise LogError(f"cannot create MCAP log {self.path}: {exc.strerror or exc}") from exc
        try:
            self._writer = Writer(
                self._file,
                chunk_size=self.config.chunk_size,
                compression=COMPRESSIONS[self.config.compression],
            )
            self._writer.start(profile="ros2" if self._ros2 else "", library=f"aefabmap/{LOG_FORMAT_VERSION}")
            if self._ros2:
                self._register_ros2_channels()
            else:
                self._image_channel = self._register_image_channel()
                self._result_channel = self._register_json_channel(self.config.result_topic,
                                                                   FrameResult.json_schema())
                self._stats_channel = self._register_json_channel(self.config.stats_topic,
                                                                  StatsMessage.json_schema())
            self._writer.add_metadata(LOG_METADATA, {
                "format_version": LOG_FORMAT_VERSION,
                "image_topic": self.config.image_topic,
                "result_topic": self.config.result_topic,
                "stats_topic": self.config.stats_topic,
                "extraction_version": str(EXTRACTION_VERSION),
            })
            if manifest is not None:
                self.add_metadata(MANIFEST_METADATA, manifest)
            if run_config is not None:
                self.add_metadata(RUN_CONFIG_METADATA, run_config)
            for name, doc in (extra_metadata or {}).items():
                self.add_metadata(name, doc)
        except (OSError, LogError) as exc:
            self._file.close()
            if isinstance(exc, LogError):
                raise
            raise LogError(f"cannot write MCAP log {self.path}: {exc.strerror or exc}") from exc
        self._last_flush = time.monotonic()
        self._seq = {self._image_channel: 0, self._result_channel: 0, self._stats_channel: 0}
        if self._ros is not None:
            self._seq[self._diagnostics_channel] = 0
        self._view_channels: dict[str, int] = {}  # registered at first use (live view on)

    # ------------------------------------------------------------------ setup
    def _register_image_channel(self) -> int:
        fds = build_file_descriptor_set(CompressedImage)
        schema_id = self._writer.register_schema(
            name=CompressedImage.DESCRIPTOR.full_name, encoding="protobuf", data=fds.SerializeToString()
        )
        return self._writer.register_channel(
            topic=self.config.image_topic, message_encoding="protobuf", schema_id=schema_id
        )

    def _register_ros2_channels(self) -> None:
        """Image, result, stats and /diagnostics channels of the ros2 profile, as rosbag2 registers
        them (runtime/aefabmap_runtime/adapters/rosbag2_mcap.py)."""
        self._ros = Rosbag2Channels(self._writer)
        self._hardware_id = socket.gethostname()  # DiagnosticStatus.hardware_id, as the ROS 2 publisher's
        self._image_channel = self._ros.add(self.config.image_topic, COMPRESSED_IMAGE_TYPE)
        self._result_channel, self._stats_channel = (
            self._ros.add(topic, STRING_TYPE, metadata={MESSAGE_KIND_KEY: kind.TITLE})
            for topic, kind in ((self.config.result_topic, FrameResult), (self.config.stats_topic, StatsMessage))
        )
        self._diagnostics_channel = self._ros.add(DIAGNOSTICS_TOPIC, DIAGNOSTIC_ARRAY_TYPE)

    def _image_message(self, payload: bytes, fmt: str, stamp_ns: int) -> bytes:
        """One serialised image message of the profile; stamp_ns: capture time (ns)."""
        if self._ros is not None:
            return self._ros.encode(self._image_channel,
                                    compressed_image(stamp_ns, fmt, payload, self.config.frame_id))
        msg = CompressedImage(frame_id=self.config.frame_id, data=bytes(payload), format=fmt)
        msg.timestamp.FromNanoseconds(stamp_ns)
        return msg.SerializeToString()

    def _text_message(self, channel: int, data: bytes) -> bytes:
        """JSON bytes as the profile's text message (a CDR std_msgs/String in ros2)."""
        return self._ros.encode(channel, text(data.decode("utf-8"))) if self._ros is not None else data

    def _register_protobuf_channel(self, topic: str, cls) -> int:
        fds = build_file_descriptor_set(cls)
        schema_id = self._writer.register_schema(
            name=cls.DESCRIPTOR.full_name, encoding="protobuf", data=fds.SerializeToString()
        )
        return self._writer.register_channel(topic=topic, message_encoding="protobuf", schema_id=schema_id)

    def _register_json_channel(self, topic: str, schema: dict) -> int:
        schema_id = self._writer.register_schema(
            name=schema["title"], encoding="jsonschema", data=json.dumps(schema).encode()
        )
        return self._writer.register_channel(topic=topic, message_encoding="json", schema_id=schema_id)

    # ------------------------------------------------------------------ writing
    def add_metadata(self, name: str, doc: dict) -> None:
        """Store a JSON-able dict as metadata record ``name`` (key ``json``)."""
        try:
            text = json.dumps(doc, sort_keys=True, default=str)
        except (TypeError, ValueError) as exc:
            raise LogError(f"metadata {name!r} is not JSON-able: {exc}") from exc
        self._guard(lambda: self._writer.add_metadata(name, {"json": text}))

    def write_image(
        self,
        payload: bytes,
        encoding: str,
        stamp_ns: int,
        *,
        sequence: int = 0,
        log_time_ns: int | None = None,
        gray: np.ndarray | None = None,
    ) -> bool:
        """Log a frame image if it is the n-th one (config.image_every); returns True if written.

        payload/encoding: the frame as received (see runtime.frames); raw frames are
        stored as lossless gray PNG (pass ``gray``, the decoded (H, W) uint8 image, to
        avoid decoding twice). stamp_ns: capture time (ns since the Unix epoch).
        """
        stamp_ns = _checked_time_ns(stamp_ns, "image stamp")
        every = self.config.image_every
        self.images_seen += 1
        if every == 0 or (self.images_seen - 1) % every != 0:
            return False
        kind, _ = classify_encoding(encoding)
        if kind == "raw":
            img = gray if gray is not None else decode_frame(payload, encoding)
            payload, _ = encode_frame(img, "png")
            fmt = "png"
        else:
            fmt = kind
        self._add(self._image_channel, self._image_message(payload, fmt, stamp_ns), log_time_ns, stamp_ns, sequence)
        self.images_written += 1
        return True

    def write_result(self, result: FrameResult | dict, *, data: bytes | None = None,
                     log_time_ns: int | None = None) -> None:
        """Log one per-frame result on the results topic.

        data: the result's ``to_json_bytes()`` when the caller has it already (a live node
        serialises once for Zenoh and the log); a dict is written as it is.
        """
        if isinstance(result, FrameResult):
            stamp, seq = result.stamp_ns, result.sequence
            data = data if data is not None else result.to_json_bytes()
        else:
            stamp, seq = result.get("stamp_ns"), result.get("sequence")
            data = data if data is not None else _json_bytes(result)
        self._add(
            self._result_channel,
            self._text_message(self._result_channel, data),
            log_time_ns,
            stamp if isinstance(stamp, int) else None,
            seq if isinstance(seq, int) else None,
        )

    def write_view(self, topic: str, data: bytes, stamp_ns: int, *, sequence: int | None = None,
                   log_time_ns: int | None = None) -> bool:
        """Log one serialised message of the live view (runtime/aefabmap_runtime/adapters/foxglove_view.py
        VIEW_PROTOBUF: place thumbnail, image annotations); its channel is registered at first use.
        Not logged (False) in the ros2 profile: ROS readers refuse protobuf channels."""
        if self._ros2:
            return False
        if topic not in self._view_channels:
            if topic not in VIEW_PROTOBUF:
                raise ConfigError(f"{topic!r} is not a live-view topic ({sorted(VIEW_PROTOBUF)})")
            channel = self._register_protobuf_channel(topic, VIEW_PROTOBUF[topic])
            self._view_channels[topic], self._seq[channel] = channel, 0
        self._add(self._view_channels[topic], data, log_time_ns, _checked_time_ns(stamp_ns, "view stamp"), sequence)
        return True

    def write_stats(self, stats: StatsMessage | dict, *, data: bytes | None = None,
                    log_time_ns: int | None = None, diagnostics: bytes | None = None) -> None:
        """Log one stats message on the stats topic (data: its JSON bytes, if already made).

        In the ros2 profile also a diagnostic_msgs/DiagnosticArray on /diagnostics: ``diagnostics``,
        the CDR the run published for these stats (rmw_zenoh.RosResultPublisher.publish_stats), else
        one made from the stats as the ROS 2 publisher makes it (status STATS_DIAGNOSTIC_NAME)."""
        if data is None:
            data = stats.to_json_bytes() if isinstance(stats, StatsMessage) else _json_bytes(stats)
        if log_time_ns is None:
            log_time_ns = time.time_ns()  # the stats and their diagnostics: one log time
        self._add(self._stats_channel, self._text_message(self._stats_channel, data), log_time_ns, None, None)
        if self._ros is not None:
            if diagnostics is None:
                diagnostics = self._stats_diagnostics(data, log_time_ns)
            self._add(self._diagnostics_channel, bytes(diagnostics), log_time_ns, None, None)

    def _stats_diagnostics(self, data: bytes, log_time_ns: int) -> bytes:
        """A DiagnosticArray of the stats' JSON ``data`` as the ROS 2 publisher makes it, without
        the node status's values (places, map size, stage times); stamp: the stats' stamp_ns."""
        try:
            doc = json.loads(data)
            stamp = doc.get("stamp_ns")
            status = node_diagnostic(doc, None, self._previous_stats, name=STATS_DIAGNOSTIC_NAME,
                                     hardware_id=self._hardware_id)
        except (TypeError, ValueError, AttributeError) as exc:  # not a stats object: no diagnostics to make
            raise LogError(f"cannot make diagnostics of stats: {type(exc).__name__}: {exc}"[:200]) from exc
        self._previous_stats = doc
        stamp = stamp if isinstance(stamp, int) and not isinstance(stamp, bool) and stamp > 0 else log_time_ns
        return self._ros.encode(self._diagnostics_channel, diagnostic_array(stamp, [status]))

    def _add(self, channel: int, data: bytes, log_time_ns, publish_time_ns, sequence) -> None:
        if self._closed:
            raise LogError(f"MCAP log {self.path} is already closed")
        now = time.time_ns()
        log_time = _checked_time_ns(log_time_ns, "log") if log_time_ns is not None else now
        publish_time = _checked_time_ns(publish_time_ns, "publish") if publish_time_ns is not None else log_time
        if sequence is None:
            sequence = self._seq[channel]
        self._seq[channel] = sequence + 1
        seq32 = int(sequence) & 0xFFFFFFFF

        def add() -> None:
            self._writer.add_message(
                channel_id=channel, log_time=log_time, data=data, publish_time=publish_time, sequence=seq32
            )
            if time.monotonic() - self._last_flush >= self.config.flush_interval_s:
                self._writer.flush()
                self._last_flush = time.monotonic()

        self._guard(add)
        self.messages_written += 1
        if self._ros is not None:
            self._ros.summary.count(channel, log_time)

    def flush(self) -> None:
        """Write out the chunk in progress now."""
        self._guard(self._writer.flush)
        self._last_flush = time.monotonic()

    def _guard(self, fn) -> None:
        try:
            fn()
        except OSError as exc:
            raise LogError(f"cannot write MCAP log {self.path}: {exc.strerror or exc}") from exc

    @property
    def bytes_written(self) -> int:
        """Bytes written to the file so far (the chunk in progress is not yet among them)."""
        return self._file.tell()

    # ------------------------------------------------------------------ lifecycle
    def abort(self) -> None:
        """Close the file without finishing it (after a write error: the MCAP writer's state
        no longer matches the file). The file stays readable up to its last complete chunk."""
        if not self._closed:
            self._closed = True
            try:
                self._file.close()
            except OSError:
                pass

    def close(self) -> None:
        """Finish the file (summary, footer) and close it; idempotent."""
        if self._closed:
            return
        self._closed = True
        try:
            if self._ros is not None:
                self._ros.finish_record(self.path.name)
            self._writer.finish()
        except OSError as exc:
            raise LogError(f"cannot finish MCAP log {self.path}: {exc.strerror or exc}") from exc
        finally:
            self._file.close()

    def __enter__(self) -> "McapLogWriter":
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()


# ============================================================================ reading

IMAGE_SCHEMAS = {
    "foxglove.CompressedImage": "foxglove",
    "sensor_msgs/msg/CompressedImage": "ros2_compressed",
    "sensor_msgs/CompressedImage": "ros2_compressed",
    "sensor_msgs/msg/Image": "ros2_raw",
    "sensor_msgs/Image": "ros2_raw",
}


@dataclass
class LoggedImage:
    """One image read from a log.

    payload/encoding: a frame as runtime.frames understands it; stamp_ns: capture time
    (ns, from the message header/timestamp); log_time_ns: MCAP log time; sequence: MCAP
    message sequence; topic: the channel topic; run: index of the run that logged it within a
    log set (log_set.LogSetReader; 0 for a single file).
    """

    topic: str
    payload: bytes
    encoding: str
    stamp_ns: int
    log_time_ns: int
    sequence: int
    run: int = 0

    def decode(self) -> np.ndarray:
        """Grayscale (H, W) uint8 image; raises FrameError (an InputError) when undecodable."""
        return decode_frame(self.payload, self.encoding)


@dataclass
class ReadStatus:
    """How far a log was read: messages_read (all topics), truncated (no clean end), reason.
    unknown_topics: topic -> messages of the channels the reader does not know (neither images,
    results, stats nor aefabmap's own unread topics, OWN_UNREAD_TOPICS): listed, not read."""

    path: str
    messages_read: int = 0
    images_read: int = 0
    truncated: bool = False
    reason: str = ""
    image_topic: str | None = None
    ignored_image_topics: list[str] = field(default_factory=list)
    undecodable_messages: int = 0
    invalid_messages: int = 0
    last_invalid: str = ""
    format_version: str | None = None
    files: list[str] = field(default_factory=list)
    profile: str | None = None  # the MCAP header's profile ("ros2"; "" for the default layout)
    unknown_topics: dict[str, int] = field(default_factory=dict)

    def describe(self) -> str:
        text = f"{self.path}: read {self.messages_read} messages ({self.images_read} images"
        text += f" on {self.image_topic})" if self.image_topic else ")"
        if self.truncated:
            text += f"; file truncated, read up to the last complete record ({self.reason})"
        if self.invalid_messages:
            text += f"; {self.invalid_messages} messages failed validation (last: {self.last_invalid})"
        if self.unknown_topics:
            # A hostile log may declare any number of channels: the line names the first few.
            listed = sorted(self.unknown_topics.items())[:MAX_DESCRIBED_TOPICS]
            text += "; not read, topics it does not know: " + ", ".join(
                f"{topic[:100]} ({n} messages)" for topic, n in listed)
            if len(self.unknown_topics) > len(listed):
                text += f" and {len(self.unknown_topics) - len(listed)} more"
        return text

    def to_dict(self) -> dict:
        return asdict(self)


def open_log_file(path: Path):
    """The file at `path` opened for binary reading; LogError when it does not exist, cannot be
    read or is not a regular file (a FIFO is refused without blocking on it)."""
    try:
        return os.fdopen(open_regular(path, follow_symlinks=True, error=LogError), "rb")
    except FileNotFoundError:
        raise LogError(f"MCAP log {path} does not exist") from None
    except OSError as exc:
        raise LogError(f"cannot read MCAP log {path}: {exc.strerror or exc}") from exc


def complete_records(f, status) -> Iterator:
    """The records of the open MCAP file `f` in file order (chunks decompressed, CRCs checked)
    up to its last complete one; a cut-off or corrupt end sets `status.truncated` and
    `status.reason` (why reading stopped) instead of raising."""
    records = StreamReader(io.BufferedReader(f, 1 << 20), validate_crcs=True).records
    while True:
        try:
            record = next(records)
        except StopIteration:
            return
        except Exception as exc:  # McapError, struct, zlib, zstd (no common base class), EOF, ...
            status.truncated = True
            status.reason = f"{type(exc).__name__}: {exc}"[:200]
            return
        yield record


class McapLogReader:
    """Single-pass reader of an aefabmap log or a ROS 2 bag, robust to truncation.

    Iterate :meth:`frames` once; while it runs, the reader collects ``results`` (the
    logged results, FrameResult), ``stats`` (StatsMessage), ``metadata`` (name -> dict) and
    ``status``. Result and stats channels are recognised by their schema name, so their
    topics are the log's own; each message is validated (runtime/aefabmap_runtime/core/records/messages.py) and an
    invalid one counted in status.invalid_messages. A log of a newer major format than this
    code reads raises LogError.
    image_topic: which image topic to read; None = the image topic the log names in its
    ``aefabmap.log`` metadata (``/camera/image`` by default) when present, else the first
    image channel met (others are listed in status.ignored_image_topics).
    """

    def __init__(self, path: str | Path, *, image_topic: str | None = None) -> None:
        self.path = Path(path)
        with open_log_file(self.path) as f:
            magic = f.read(8)
        if magic != b"\x89MCAP0\r\n":
            raise LogError(f"{self.path} is not an MCAP file (bad magic)")
        self.image_topic = image_topic
        self.results: list[FrameResult] = []
        self.stats: list[StatsMessage] = []
        self.metadata: dict[str, dict] = {}
        self.status = ReadStatus(str(self.path))
        self._spent = False

    @property
    def manifest(self) -> dict | None:
        return self.metadata.get(MANIFEST_METADATA)

    @property
    def run_config(self) -> dict | None:
        return self.metadata.get(RUN_CONFIG_METADATA)

    @property
    def format_version(self) -> tuple[int, int] | None:
        """(major, minor) of the log's format; None for logs not written by aefabmap."""
        meta = self.metadata.get(LOG_METADATA)
        return check_log_version(self.path, meta) if meta is not None else None

    @property
    def extraction_version(self) -> int | None:
        """features.EXTRACTION_VERSION of the build that wrote the log; None when the log does not
        say (written before it was recorded, not by aefabmap, or not a small positive integer)."""
        value = (self.metadata.get(LOG_METADATA) or {}).get("extraction_version")
        if isinstance(value, str) and 0 < len(value) <= 6 and value.isascii() and value.isdigit() and int(value) > 0:
            return int(value)
        return None

    def _preferred_image_topic(self) -> str:
        topic = (self.metadata.get(LOG_METADATA) or {}).get("image_topic")
        return topic if isinstance(topic, str) and topic else IMAGE_TOPIC

    def frames(self) -> Iterator[LoggedImage]:
        """Yield the images of the chosen topic in file order (single pass)."""
        if self._spent:
            raise LogError(f"{self.path}: a log reader can be iterated only once")
        self._spent = True
        schemas: dict[int, Schema] = {}
        channels: dict[int, Channel] = {}
        kinds: dict[int, str] = {}
        json_kinds: dict[int, type] = {}
        ros_decoders: dict[int, object] = {}
        chosen: int | None = None
        with open_log_file(self.path) as f:
            for record in complete_records(f, self.status):
                if isinstance(record, Header):
                    self.status.profile = record.profile
                elif isinstance(record, Schema):
                    schemas[record.id] = record
                elif isinstance(record, Channel):
                    channels[record.id] = record
                    schema = schemas.get(record.schema_id)
                    kind = IMAGE_SCHEMAS.get(schema.name) if schema is not None else None
                    if record.topic == PLACE_IMAGE_TOPIC and record.topic != self.image_topic:
                        kind = None  # the live view's place thumbnails: not the camera
                    if kind is not None:
                        kinds[record.id] = kind
                        chosen = self._choose(record, chosen, channels)
                    elif schema is not None and schema.name in _JSON_MESSAGES and record.message_encoding == "json":
                        json_kinds[record.id] = _JSON_MESSAGES[schema.name]
                    elif _is_ros2_text_channel(record, schema):
                        json_kinds[record.id] = _JSON_MESSAGES[record.metadata[MESSAGE_KIND_KEY]]
                    elif record.topic not in OWN_UNREAD_TOPICS:
                        self.status.unknown_topics.setdefault(record.topic, 0)
                elif isinstance(record, Metadata):
                    self._take_metadata(record)
                elif isinstance(record, Message):
                    self.status.messages_read += 1
                    channel = channels.get(record.channel_id)
                    if channel is None:
                        continue
                    if record.channel_id in kinds:
                        if record.channel_id != chosen:
                            continue
                        image = self._decode_image(record, channel, kinds[record.channel_id], schemas, ros_decoders)
                        if image is not None:
                            self.status.images_read += 1
                            yield image
                    elif record.channel_id in json_kinds:
                        self._take_json(record, json_kinds[record.channel_id], cdr=channel.message_encoding == "cdr")
                    elif channel.topic in self.status.unknown_topics:
                        self.status.unknown_topics[channel.topic] += 1

    def _choose(self, channel: Channel, chosen: int | None, channels: dict[int, Channel]) -> int | None:
        topic = channel.topic
        if self.image_topic is not None:
            pick = chosen is None and topic == self.image_topic
        else:
            preferred = self._preferred_image_topic()
            pick = chosen is None or (topic == preferred and channels[chosen].topic != preferred)
        if pick:
            if chosen is not None:
                self._ignore(channels[chosen].topic)
            self.status.image_topic = topic
            return channel.id
        if channel.id != chosen:
            self._ignore(topic)
        return chosen

    def _ignore(self, topic: str) -> None:
        if topic not in self.status.ignored_image_topics and topic != self.status.image_topic:
            self.status.ignored_image_topics.append(topic)

    def _take_metadata(self, record: Metadata) -> None:
        self.metadata[record.name] = _metadata_dict(record)
        if record.name == LOG_METADATA:
            check_log_version(self.path, self.metadata[record.name])  # LogError: newer major
            self.status.format_version = str(self.metadata[record.name].get("format_version"))

    def _take_json(self, record: Message, kind: type, *, cdr: bool = False) -> None:
        """Validate and keep one result/stats message (cdr: JSON inside a std_msgs/String)."""
        try:
            message = kind.from_json(decode_string_cdr(record.data) if cdr else record.data)
        except InputError as exc:  # FrameError (broken CDR) included
            self.status.invalid_messages += 1
            self.status.last_invalid = str(exc)[:200]
            return
        (self.results if kind is FrameResult else self.stats).append(message)

    def _count_undecodable(self, why: str) -> None:
        self.status.undecodable_messages += 1
        self.status.invalid_messages += 1
        self.status.last_invalid = why[:200]

    def _decode_cdr_compressed(self, record: Message, channel: Channel) -> LoggedImage | None:
        """A CDR CompressedImage through the strict reader the live subscriber uses; a broken
        message is counted with its reason (status.last_invalid) and skipped."""
        try:
            image = decode_compressed_cdr(record.data)
        except FrameError as exc:
            self._count_undecodable(f"{exc.reason}: {exc}")
            return None
        return LoggedImage(channel.topic, image.payload, image.encoding, image.stamp_ns or record.publish_time,
                           record.log_time, record.sequence)

    def _decode_image(self, record, channel, kind, schemas, ros_decoders) -> LoggedImage | None:
        if kind == "ros2_compressed" and channel.message_encoding == "cdr":
            return self._decode_cdr_compressed(record, channel)
        try:
            if kind == "foxglove":
                msg = CompressedImage.FromString(record.data)
                stamp = msg.timestamp.ToNanoseconds() or record.publish_time
                return LoggedImage(
                    channel.topic,
                    bytes(msg.data),
                    compressed_format_to_encoding(msg.format),
                    int(stamp),
                    record.log_time,
                    record.sequence,
                )
            decoder = ros_decoders.get(channel.id)
            if decoder is None:
                from mcap_ros2.decoder import DecoderFactory

                decoder = DecoderFactory().decoder_for(channel.message_encoding, schemas.get(channel.schema_id))
                if decoder is None:
                    raise LogError(f"no ROS 2 decoder for channel {channel.topic}")
                ros_decoders[channel.id] = decoder
            msg = decoder(record.data)
            stamp = int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)
            if kind == "ros2_compressed":
                payload = bytes(msg.data)
                encoding = compressed_format_to_encoding(msg.format)
            else:
                try:
                    payload, encoding = pack_raw_rows(
                        bytes(msg.data), str(msg.encoding), int(msg.width), int(msg.height), int(msg.step)
                    )
                except FrameError as exc:
                    # Keep the frame so the consumer counts it as bad, with the reason.
                    payload, encoding = bytes(msg.data), f"unknown/{msg.encoding}:{exc.reason}"
            return LoggedImage(channel.topic, payload, encoding, stamp or record.publish_time, record.log_time,
                               record.sequence)
        except (LogError, ImageDecodeError):
            raise
        except Exception as exc:  # malformed message bytes: count and skip, keep reading
            self._count_undecodable(f"{channel.topic}: {type(exc).__name__}: {exc}")
            return None


#: JSON message type of each aefabmap schema name.
_JSON_MESSAGES: dict[str, type] = {RESULT_SCHEMA_NAME: FrameResult, STATS_SCHEMA_NAME: StatsMessage}


def _is_ros2_text_channel(channel: Channel, schema: Schema | None) -> bool:
    """A ros2-profile result/stats channel: CDR std_msgs/String marked with MESSAGE_KIND_KEY."""
    return (schema is not None and schema.name == STRING_TYPE and channel.message_encoding == "cdr"
            and channel.metadata.get(MESSAGE_KIND_KEY) in _JSON_MESSAGES)


def log_size_bytes(path: str | Path) -> int:
    """Size of a log file in bytes (0 when missing)."""
    try:
        return os.path.getsize(path)
    except OSError:
        return 0


def _metadata_dict(record: Metadata) -> dict:
    """A metadata record as a dict: the parsed ``json`` value when that is its only key."""
    data = dict(record.metadata)
    if "json" in data and len(data) == 1:
        try:
            return json.loads(data["json"])
        except ValueError:
            pass
    return data


def read_log_metadata(path: str | Path, *, max_records: int = 10_000) -> dict[str, dict]:
    """Metadata records (name -> dict) found before the first chunk/message of a log.

    aefabmap logs write their metadata at open, so this is cheap and survives truncation.
    """
    McapLogReader(path)  # existence and magic checks (LogError)
    out: dict[str, dict] = {}
    with open_log_file(Path(path)) as f:
        records = StreamReader(f, emit_chunks=True).records
        for _ in range(max_records):
            try:
                record = next(records)
            except StopIteration:
                break
            except Exception:  # truncated / corrupt: return what was read
                break
            if isinstance(record, Metadata):
                out[record.name] = _metadata_dict(record)
                if record.name == LOG_METADATA:
                    check_log_version(path, out[record.name])
            elif not isinstance(record, (Header, Schema, Channel)):
                break
    return out
