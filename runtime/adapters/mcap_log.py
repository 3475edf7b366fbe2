"""MCAP logging of a run and reading logs back for replay.

Log layout written by :class:`McapLogWriter`:

============== ====================================== ===============================
topic          schema / encoding                       content
============== ====================================== ===============================
/camera/image  ``foxglove.CompressedImage`` (protobuf) every n-th processed frame (jpeg/png;
                                                       raw frames are stored as gray PNG)
/lcd/result    ``aefabmap.LcdResult`` (jsonschema/json) one per processed frame
/lcd/stats     ``aefabmap.LcdStats`` (jsonschema/json)  periodic run statistics
============== ====================================== ===============================

Metadata records ``aefabmap.manifest`` and ``aefabmap.run_config`` each hold one key
``json`` with the JSON text of the bundle manifest / run configuration; they are written
at open, so they survive a crash. Message ``sequence`` = the frame's sequence number in the
run (0-based count of processed frames); image ``timestamp`` = the frame's capture stamp.

Crash safety: zstd chunks of ``chunk_size`` bytes (256 KiB by default) written through an
unbuffered file, and a forced chunk flush every ``flush_interval_s`` seconds: a SIGKILL
loses at most one chunk or ``flush_interval_s`` of data. :class:`McapLogReader` reads
such a file (no summary) sequentially up to its last complete record and reports
``truncated`` and ``messages_read``.

The reader also takes ROS 2 bags (``sensor_msgs/msg/CompressedImage`` and
``sensor_msgs/msg/Image``, CDR via mcap-ros2-support).
"""

from __future__ import annotations

import io
import json
import os
import struct
import time
import zlib
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from mcap.exceptions import McapError
from mcap.records import Channel, Header, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer
from mcap_protobuf.schema import build_file_descriptor_set

from aefabmap.errors import ConfigError, ImageDecodeError, LogError
from aefabmap.runtime.adapters.frames import (
    FrameError,
    classify_encoding,
    compressed_format_to_encoding,
    decode_frame,
    encode_frame,
    pack_raw_rows,
)

IMAGE_TOPIC = "/camera/image"
RESULT_TOPIC = "/lcd/result"
STATS_TOPIC = "/lcd/stats"
MANIFEST_METADATA = "aefabmap.manifest"
RUN_CONFIG_METADATA = "aefabmap.run_config"
LOG_FORMAT_VERSION = "1"

RESULT_SCHEMA = {
    "title": "aefabmap.LcdResult",
    "description": "loop-closure result of one frame (runtime.pipeline.FrameResult.to_dict() + transport fields)",
    "type": "object",
    "properties": {
        "sequence": {"type": "integer", "description": "0-based index of the processed frame"},
        "stamp_ns": {"type": "integer", "description": "capture time, ns since the Unix epoch"},
        "n_keypoints": {"type": "integer"},
        "n_words": {"type": "integer"},
        "best_place": {"type": ["integer", "null"], "description": "best candidate place id"},
        "best_frame": {"type": ["integer", "null"], "description": "sequence of the frame that made best_place"},
        "score": {"type": "number", "description": "FAB-MAP probability or BoW similarity of best_place"},
        "p_new": {"type": ["number", "null"], "description": "FAB-MAP new-place probability"},
        "loop": {"type": "boolean", "description": "loop closure accepted"},
        "inserted_frame": {"type": ["integer", "null"]},
        "inserted_place": {"type": ["integer", "null"]},
        "evicted_place": {"type": ["integer", "null"]},
        "n_places": {"type": "integer"},
        "timings_ms": {"type": "object", "additionalProperties": {"type": "number"}},
        "probability": {"type": ["number", "null"], "description": "FAB-MAP posterior of best_place"},
        "llr": {"type": ["number", "null"], "description": "log-likelihood ratio best_place vs new place, nats"},
        "verified": {"type": "boolean", "description": "a candidate passed geometric (+ temporal) verification"},
        "verified_place": {"type": ["integer", "null"], "description": "place id of the verified candidate"},
        "verified_frame": {"type": ["integer", "null"], "description": "sequence of the frame that made verified_place"},
        "inliers": {"type": "integer", "description": "inliers of the accepted geometry (or of the best attempt)"},
        "matches": {"type": "integer", "description": "putative keypoint matches behind `inliers`"},
        "geometry_model": {"type": ["string", "null"], "enum": ["F", "H", None],
                           "description": "F: fundamental matrix, H: homography"},
        "geometry": {"type": ["array", "null"], "items": {"type": "array", "items": {"type": "number"}},
                     "description": "3x3 row-major matrix, place image -> query image, original pixels"},
        "candidates_tried": {"type": "integer", "description": "places verified for this frame"},
        "geometry_ok": {"type": "boolean", "description": "geometric check passed (before the temporal check)"},
        "temporal_ok": {"type": ["boolean", "null"], "description": "temporal check passed (null: off)"},
        "candidates": {"type": "array", "description": "top places and every place checked (core.detector.Candidate)",
                       "items": {"type": "object", "properties": {
                           "place": {"type": "integer"}, "frame": {"type": "integer"}, "rank": {"type": "integer"},
                           "probability": {"type": ["number", "null"]}, "llr": {"type": ["number", "null"]},
                           "similarity": {"type": ["number", "null"]}, "checked": {"type": "boolean"},
                           "source": {"type": ["string", "null"]}, "verified": {"type": "boolean"},
                           "inliers": {"type": "integer"}, "matches": {"type": "integer"},
                           "model": {"type": ["string", "null"]}, "nfa": {"type": ["number", "null"]}}}},
        "frame_seq": {"type": ["integer", "null"], "description": "publisher sequence number (live runs)"},
        "latency_ms": {"type": "number", "description": "taken from the ring -> result, ms (live runs)"},
        "age_ms": {"type": "number", "description": "capture stamp -> result, ms (live runs, synced clocks)"},
    },
}

STATS_SCHEMA = {
    "title": "aefabmap.LcdStats",
    "description": "periodic statistics of a streaming run",
    "type": "object",
    "properties": {
        "stamp_ns": {"type": "integer"},
        "uptime_s": {"type": "number"},
        "frames_received": {"type": "integer"},
        "frames_processed": {"type": "integer"},
        "dropped": {"type": "integer", "description": "sequence gaps (ring overflow or network)"},
        "bad": {"type": "object", "additionalProperties": {"type": "integer"}},
        "bad_total": {"type": "integer"},
        "loops": {"type": "integer"},
        "rss_mb": {"type": "number"},
        "latency_ms": {"type": "object", "properties": {"p50": {"type": "number"}, "p95": {"type": "number"}}},
        "fps": {"type": "number", "description": "processed frames per second since the last stats"},
    },
}

COMPRESSIONS = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}


@dataclass(frozen=True)
class McapLogConfig:
    """Settings of the MCAP writer.

    chunk_size: bytes of uncompressed messages per chunk (smaller = less lost on a crash).
    compression: "zstd", "lz4" or "none".
    flush_interval_s: force out the chunk in progress at least this often (seconds).
    image_every: log every n-th processed frame's image (1 = all; needed for an exact replay).
    """

    chunk_size: int = 256 * 1024
    compression: str = "zstd"
    flush_interval_s: float = 2.0
    image_every: int = 1
    image_topic: str = IMAGE_TOPIC
    result_topic: str = RESULT_TOPIC
    stats_topic: str = STATS_TOPIC
    frame_id: str = "camera"

    def __post_init__(self) -> None:
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

    def __init__(self, path: Path) -> None:
        self._f = open(path, "wb", buffering=0)  # noqa: SIM115 - closed in close()
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


def _json_bytes(doc: dict) -> bytes:
    return json.dumps(doc, separators=(",", ":"), allow_nan=True).encode()


class McapLogWriter:
    """Context manager writing one run to an MCAP file (see module docstring for the layout).

    path: output file (parent directory must exist and be writable).
    manifest / run_config: JSON-able dicts stored as metadata at open.
    Raises LogError (naming the path) when the file cannot be created or written.
    """

    def __init__(
        self,
        path: str | Path,
        config: McapLogConfig | None = None,
        *,
        manifest: dict | None = None,
        run_config: dict | None = None,
    ) -> None:
        self.path = Path(path)
        self.config = config or McapLogConfig()
        self.images_written = 0
        self.images_seen = 0
        self.messages_written = 0
        self._closed = False
        try:
            self._file = _UnbufferedFile(self.path)
        except OSError as exc:
            raise LogError(f"cannot create MCAP log {self.path}: {exc.strerror or exc}") from exc
        try:
            self._writer = Writer(
                self._file,
                chunk_size=self.config.chunk_size,
                compression=COMPRESSIONS[self.config.compression],
            )
            self._writer.start(profile="", library=f"aefabmap/{LOG_FORMAT_VERSION}")
            self._image_channel = self._register_image_channel()
            self._result_channel = self._register_json_channel(self.config.result_topic, RESULT_SCHEMA)
            self._stats_channel = self._register_json_channel(self.config.stats_topic, STATS_SCHEMA)
            self._writer.add_metadata("aefabmap.log", {"format_version": LOG_FORMAT_VERSION})
            if manifest is not None:
                self.add_metadata(MANIFEST_METADATA, manifest)
            if run_config is not None:
                self.add_metadata(RUN_CONFIG_METADATA, run_config)
        except OSError as exc:
            self._file.close()
            raise LogError(f"cannot write MCAP log {self.path}: {exc.strerror or exc}") from exc
        self._last_flush = time.monotonic()
        self._seq = {self._image_channel: 0, self._result_channel: 0, self._stats_channel: 0}

    # ------------------------------------------------------------------ setup
    def _register_image_channel(self) -> int:
        fds = build_file_descriptor_set(CompressedImage)
        schema_id = self._writer.register_schema(
            name=CompressedImage.DESCRIPTOR.full_name, encoding="protobuf", data=fds.SerializeToString()
        )
        return self._writer.register_channel(
            topic=self.config.image_topic, message_encoding="protobuf", schema_id=schema_id
        )

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
        msg = CompressedImage(frame_id=self.config.frame_id, data=bytes(payload), format=fmt)
        msg.timestamp.FromNanoseconds(int(stamp_ns))
        self._add(self._image_channel, msg.SerializeToString(), log_time_ns, int(stamp_ns), sequence)
        self.images_written += 1
        return True

    def write_result(self, result: dict, *, log_time_ns: int | None = None) -> None:
        """Log one per-frame result dict (JSON) on the results topic."""
        stamp = result.get("stamp_ns")
        seq = result.get("sequence")
        self._add(
            self._result_channel,
            _json_bytes(result),
            log_time_ns,
            stamp if isinstance(stamp, int) else None,
            seq if isinstance(seq, int) else None,
        )

    def write_stats(self, stats: dict, *, log_time_ns: int | None = None) -> None:
        """Log one stats dict (JSON) on the stats topic."""
        self._add(self._stats_channel, _json_bytes(stats), log_time_ns, None, None)

    def _add(self, channel: int, data: bytes, log_time_ns, publish_time_ns, sequence) -> None:
        if self._closed:
            raise LogError(f"MCAP log {self.path} is already closed")
        now = time.time_ns()
        log_time = int(log_time_ns) if log_time_ns is not None else now
        publish_time = int(publish_time_ns) if publish_time_ns is not None else log_time
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

    def flush(self) -> None:
        """Write out the chunk in progress now."""
        self._guard(self._writer.flush)
        self._last_flush = time.monotonic()

    def _guard(self, fn) -> None:
        try:
            fn()
        except OSError as exc:
            raise LogError(f"cannot write MCAP log {self.path}: {exc.strerror or exc}") from exc

    # ------------------------------------------------------------------ lifecycle
    def close(self) -> None:
        """Finish the file (summary, footer) and close it; idempotent."""
        if self._closed:
            return
        self._closed = True
        try:
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
    message sequence; topic: the channel topic.
    """

    topic: str
    payload: bytes
    encoding: str
    stamp_ns: int
    log_time_ns: int
    sequence: int

    def decode(self) -> np.ndarray:
        """Grayscale (H, W) uint8 image; raises FrameError (an InputError) when undecodable."""
        return decode_frame(self.payload, self.encoding)


@dataclass
class ReadStatus:
    """How far a log was read: messages_read (all topics), truncated (no clean end), reason."""

    path: str
    messages_read: int = 0
    images_read: int = 0
    truncated: bool = False
    reason: str = ""
    image_topic: str | None = None
    ignored_image_topics: list[str] = field(default_factory=list)
    undecodable_messages: int = 0

    def describe(self) -> str:
        text = f"{self.path}: read {self.messages_read} messages ({self.images_read} images"
        text += f" on {self.image_topic})" if self.image_topic else ")"
        if self.truncated:
            text += f"; file truncated, read up to the last complete record ({self.reason})"
        return text

    def to_dict(self) -> dict:
        return asdict(self)


class McapLogReader:
    """Single-pass reader of an aefabmap log or a ROS 2 bag, robust to truncation.

    Iterate :meth:`frames` once; while it runs, the reader collects ``results`` (the
    logged /lcd/result dicts), ``stats``, ``metadata`` (name -> dict) and ``status``.
    image_topic: which image topic to read; None = ``/camera/image`` when present, else
    the first image channel met (others are listed in status.ignored_image_topics).
    """

    def __init__(self, path: str | Path, *, image_topic: str | None = None) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise LogError(f"MCAP log {self.path} does not exist")
        with open(self.path, "rb") as f:
            magic = f.read(8)
        if magic != b"\x89MCAP0\r\n":
            raise LogError(f"{self.path} is not an MCAP file (bad magic)")
        self.image_topic = image_topic
        self.results: list[dict] = []
        self.stats: list[dict] = []
        self.metadata: dict[str, dict] = {}
        self.status = ReadStatus(str(self.path))
        self._spent = False

    @property
    def manifest(self) -> dict | None:
        return self.metadata.get(MANIFEST_METADATA)

    @property
    def run_config(self) -> dict | None:
        return self.metadata.get(RUN_CONFIG_METADATA)

    def frames(self) -> Iterator[LoggedImage]:
        """Yield the images of the chosen topic in file order (single pass)."""
        if self._spent:
            raise LogError(f"{self.path}: a log reader can be iterated only once")
        self._spent = True
        schemas: dict[int, Schema] = {}
        channels: dict[int, Channel] = {}
        kinds: dict[int, str] = {}
        ros_decoders: dict[int, object] = {}
        chosen: int | None = None
        with open(self.path, "rb") as f:
            records = StreamReader(io.BufferedReader(f, 1 << 20), validate_crcs=True).records
            while True:
                try:
                    record = next(records)
                except StopIteration:
                    break
                except (McapError, struct.error, ValueError, EOFError, zlib.error, MemoryError) as exc:
                    self.status.truncated = True
                    self.status.reason = f"{type(exc).__name__}: {exc}"[:200]
                    break
                except Exception as exc:  # zstd errors have no common base class we can import
                    self.status.truncated = True
                    self.status.reason = f"{type(exc).__name__}: {exc}"[:200]
                    break
                if isinstance(record, Schema):
                    schemas[record.id] = record
                elif isinstance(record, Channel):
                    channels[record.id] = record
                    schema = schemas.get(record.schema_id)
                    kind = IMAGE_SCHEMAS.get(schema.name) if schema is not None else None
                    if kind is not None:
                        kinds[record.id] = kind
                        chosen = self._choose(record, chosen, channels)
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
                    elif channel.message_encoding == "json":
                        self._take_json(record, channel)

    def _choose(self, channel: Channel, chosen: int | None, channels: dict[int, Channel]) -> int | None:
        topic = channel.topic
        if self.image_topic is not None:
            pick = chosen is None and topic == self.image_topic
        else:
            pick = chosen is None or (topic == IMAGE_TOPIC and channels[chosen].topic != IMAGE_TOPIC)
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

    def _take_json(self, record: Message, channel: Channel) -> None:
        if channel.topic not in (RESULT_TOPIC, STATS_TOPIC):
            return
        try:
            doc = json.loads(record.data)
        except ValueError:
            self.status.undecodable_messages += 1
            return
        (self.results if channel.topic == RESULT_TOPIC else self.stats).append(doc)

    def _decode_image(self, record, channel, kind, schemas, ros_decoders) -> LoggedImage | None:
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
        except Exception:  # malformed message bytes: count and skip, keep reading
            self.status.undecodable_messages += 1
            return None


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
    with open(path, "rb") as f:
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
            elif not isinstance(record, (Header, Schema, Channel)):
                break
    return out
