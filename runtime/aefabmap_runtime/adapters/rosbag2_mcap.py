"""MCAP written the way rosbag2 writes it: the channels and metadata of the log's ros2 profile.

What rosbag2's MCAP storage plugin (rosbag2_storage_mcap) puts in a file, and :class:`Rosbag2Channels`
puts there too:

- one ``ros2msg`` schema per message type (the definitions of runtime/aefabmap_runtime/adapters/ros_cdr.py,
  as rosbag2 and rosbags generate them) and one ``cdr`` channel per topic;
- channel metadata ``offered_qos_profiles``: the QoS profiles the topic's publishers offered, a YAML
  list in rosbag2's metadata version 8 form (policies as integers: what every distribution reads,
  and what rosbag2 assumes of a file without a ``rosbag2`` record); ``ros2 bag play`` offers that
  QoS again. Ours is PUBLISHER_QOS, the profile of the node's ROS 2 publishers (rmw's default);
- channel metadata ``topic_type_hash``: the type's RIHS01 hash (Iron and later; Humble ignores it);
- metadata record ``rosbag2``, key ``serialized_metadata``: the bag's metadata as a rosbag2
  ``metadata.yaml`` holds it (version 8, storage ``mcap``, this file, start, duration, message
  count per topic with its QoS), written when the file is finished (:meth:`Rosbag2Summary.record`):
  ``ros2 bag info`` and ``ros2 bag reindex`` read it. A file cut off before its end has none; rosbag2
  and rosbags then count from the file itself.

Messages are serialised by mcap-ros2-support's CDR encoder from those definitions. YAML is written
as JSON, the subset of YAML that yaml-cpp (rosbag2) and ruamel (rosbags) both read, every string
quoted by the JSON encoder.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any

from mcap.writer import Writer
from mcap_ros2._dynamic import serialize_dynamic  # the encoder behind mcap_ros2.writer.Writer

from aefabmap_runtime.errors import LogError
from aefabmap_runtime.adapters.ros_cdr import RIHS01_OF
from aefabmap_runtime.adapters.ros_cdr import MSGDEFS, DiagnosticStatus

#: Name and key of rosbag2's metadata record.
ROSBAG2_METADATA = "rosbag2"
ROSBAG2_METADATA_KEY = "serialized_metadata"
QOS_KEY = "offered_qos_profiles"
TYPE_HASH_KEY = "topic_type_hash"
#: rosbag2 metadata version written (Iron, Jazzy): QoS policies as integers, ``ros_distro`` present.
ROSBAG2_VERSION = 8
#: rmw's QoS policy values (rmw/types.h) in the integer form of metadata version 8.
KEEP_LAST, RELIABLE, VOLATILE, LIVELINESS_SYSTEM_DEFAULT = 1, 1, 2, 0
#: rmw_qos_profile_default (keep last 10, reliable, volatile, unset durations): the profile of the
#: node's ROS 2 publishers (rmw_zenoh's default QoS token). Images are logged under it too: a
#: reliable offer is what both reliable and best-effort subscribers accept on playback.
PUBLISHER_QOS: dict[str, Any] = {
    "history": KEEP_LAST,
    "depth": 10,
    "reliability": RELIABLE,
    "durability": VOLATILE,
    "deadline": {"sec": 0, "nsec": 0},
    "lifespan": {"sec": 0, "nsec": 0},
    "liveliness": LIVELINESS_SYSTEM_DEFAULT,
    "liveliness_lease_duration": {"sec": 0, "nsec": 0},
    "avoid_ros_namespace_conventions": False,
}
_INT32_MAX = 2**31 - 1


def qos_yaml(profiles: list[dict[str, Any]]) -> str:
    """``offered_qos_profiles`` text of a list of QoS profiles (rosbag2 version 8 form)."""
    return json.dumps(profiles)


def ros_time(stamp_ns: int) -> dict[str, int]:
    """builtin_interfaces/Time of a stamp in ns (negative: 0; past int32 seconds: the last second)."""
    sec, nanosec = divmod(max(0, int(stamp_ns)), 1_000_000_000)
    return {"sec": min(sec, _INT32_MAX), "nanosec": nanosec}


def header(stamp_ns: int, frame_id: str = "") -> dict:
    """std_msgs/Header of a stamp (ns) and frame."""
    return {"stamp": ros_time(stamp_ns), "frame_id": frame_id}


def compressed_image(stamp_ns: int, fmt: str, data: bytes, frame_id: str = "") -> dict:
    """sensor_msgs/msg/CompressedImage; fmt ``jpeg`` or ``png``, data the compressed bytes."""
    return {"header": header(stamp_ns, frame_id), "format": fmt, "data": bytes(data)}


def text(data: str) -> dict:
    """std_msgs/msg/String."""
    return {"data": data}


def diagnostic_array(stamp_ns: int, statuses: list[DiagnosticStatus] | tuple[DiagnosticStatus, ...]) -> dict:
    """diagnostic_msgs/msg/DiagnosticArray of statuses, header stamp ``stamp_ns``."""
    return {"header": header(stamp_ns), "status": [
        {"level": s.level, "name": s.name, "message": s.message, "hardware_id": s.hardware_id,
         "values": [{"key": k, "value": v} for k, v in s.values]} for s in statuses]}


@dataclass
class TopicCount:
    """One channel as rosbag2's metadata lists it: topic, type, serialization format, the
    ``offered_qos_profiles`` and ``topic_type_hash`` texts, and its messages in the file."""

    topic: str
    type: str
    serialization_format: str
    offered_qos_profiles: str
    type_hash: str
    message_count: int = 0


class Rosbag2Summary:
    """What a file holds, counted as its messages are written, for its ``rosbag2`` record.

    Channels are added with :meth:`add_channel` (ROS 2 ``cdr`` channels only: rosbag2 lists no
    other) and messages counted with :meth:`count`; :meth:`record` is the record's content.
    """

    def __init__(self) -> None:
        self.topics: dict[int, TopicCount] = {}
        self.start_ns: int | None = None
        self.end_ns = 0

    def add_channel(self, channel_id: int, topic: str, ros_type: str, metadata: dict[str, str]) -> None:
        self.topics[channel_id] = TopicCount(topic, ros_type, "cdr", metadata.get(QOS_KEY, ""),
                                             metadata.get(TYPE_HASH_KEY, ""))

    def count(self, channel_id: int, log_time_ns: int) -> None:
        """One message of the channel, logged at log_time_ns (rosbag2's receive time)."""
        entry = self.topics.get(channel_id)
        if entry is None:
            return
        entry.message_count += 1
        self.start_ns = log_time_ns if self.start_ns is None else min(self.start_ns, log_time_ns)
        self.end_ns = max(self.end_ns, log_time_ns)

    def record(self, file_name: str, *, ros_distro: str = "") -> dict[str, str]:
        """The ``rosbag2`` metadata record of a file named file_name (its base name)."""
        count = sum(t.message_count for t in self.topics.values())
        start = self.start_ns or 0
        duration = self.end_ns - start if self.start_ns is not None else 0
        doc = {
            "version": ROSBAG2_VERSION,
            "storage_identifier": "mcap",
            "duration": {"nanoseconds": duration},
            "starting_time": {"nanoseconds_since_epoch": start},
            "message_count": count,
            "topics_with_message_count": [
                {"topic_metadata": {"name": t.topic, "type": t.type, "serialization_format": t.serialization_format,
                                    "offered_qos_profiles": t.offered_qos_profiles,
                                    "type_description_hash": t.type_hash},
                 "message_count": t.message_count}
                for t in self.topics.values()
            ],
            "compression_format": "",  # chunk compression is MCAP's own, not rosbag2's
            "compression_mode": "",
            "relative_file_paths": [file_name],
            "files": [{"path": file_name, "starting_time": {"nanoseconds_since_epoch": start},
                       "duration": {"nanoseconds": duration}, "message_count": count}],
            "custom_data": {},
            "ros_distro": ros_distro,
        }
        return {ROSBAG2_METADATA_KEY: json.dumps(doc)}


class Rosbag2Channels:
    """The ros2-profile channels of one MCAP ``writer`` (started with profile ``ros2``): schemas and
    channels registered as rosbag2 does, messages serialised by the library, counted in
    ``summary`` for the file's ``rosbag2`` record (:meth:`finish_record`)."""

    def __init__(self, writer: Writer) -> None:
        self._writer = writer
        self._schemas: dict[str, int] = {}
        self._encoders: dict[int, Any] = {}
        self.summary = Rosbag2Summary()

    def add(self, topic: str, ros_type: str, *, metadata: dict[str, str] | None = None,
            qos: list[dict[str, Any]] | None = None) -> int:
        """Register ``topic`` of ``ros_type`` (a type of ros_cdr.MSGDEFS) offered with ``qos``
        (default: [PUBLISHER_QOS]); metadata: further channel metadata. Returns the channel id."""
        if ros_type not in self._schemas:
            self._schemas[ros_type] = self._writer.register_schema(ros_type, "ros2msg", MSGDEFS[ros_type].encode())
        meta = {QOS_KEY: qos_yaml(qos if qos is not None else [PUBLISHER_QOS]),
                TYPE_HASH_KEY: RIHS01_OF.get(ros_type, ""), **(metadata or {})}
        channel = self._writer.register_channel(topic, "cdr", self._schemas[ros_type], meta)
        self._encoders[channel] = serialize_dynamic(ros_type, MSGDEFS[ros_type])[ros_type]
        self.summary.add_channel(channel, topic, ros_type, meta)
        return channel

    def encode(self, channel: int, message: dict) -> bytes:
        """The CDR of ``message`` (a dict of the channel type's fields); LogError when it does not
        fit the type (a value out of its range, a field missing)."""
        try:
            return self._encoders[channel](message)
        except Exception as exc:  # noqa: BLE001 - the library raises struct, type and its own errors
            topic = self.summary.topics[channel].topic
            raise LogError(f"cannot serialise a message of {topic[:100]}: {type(exc).__name__}: {exc}"[:200]) \
                from exc

    def finish_record(self, file_name: str) -> None:
        """Write the file's ``rosbag2`` metadata record (before the writer's finish)."""
        self._writer.add_metadata(ROSBAG2_METADATA, self.summary.record(file_name))
