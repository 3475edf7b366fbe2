"""Any ROS bag as a replay source: rosbag2 directories (metadata.yaml; sqlite3 or MCAP
storage), bare ``.db3`` and ``.mcap`` files, and ROS 1 ``.bag`` files, read with rosbags.

rosbags is an optional dependency (``pip install aefabmap[ros]``): it is imported when a bag
is opened, so a board without it still runs and replays its own MCAP logs.

The images are decoded by the same CDR reader as the live rmw_zenoh subscriber
(runtime/aefabmap_runtime/adapters/ros_cdr.py; ROS 1 messages through rosbags' deserializer into the same
field mapping), so a frame looks the same whichever way it came. Topic choice: the
``sensor_msgs/msg/Image`` and ``CompressedImage`` topics of the bag; with several and no
``image_topic`` given, :class:`LogError` lists them (a depth topic is an image topic too,
and guessing would replay the wrong camera).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

from aefabmap_runtime.errors import LogError
from aefabmap_runtime.adapters.frames import FrameError
from aefabmap_runtime.adapters.mcap_log import (
    LOG_METADATA,
    LoggedImage,
    ReadStatus,
    complete_records,
    open_log_file,
    read_log_metadata,
)
from aefabmap_runtime.adapters.ros_cdr import (
    COMPRESSED_IMAGE_TYPE,
    DECODERS,
    IMAGE_TYPE,
    compressed_from_fields,
    image_from_fields,
)

INSTALL_HINT = "install aefabmap[ros] (pip install 'aefabmap[ros]') to read ROS bags"
_IMAGE_TYPES = (IMAGE_TYPE, COMPRESSED_IMAGE_TYPE)


def is_ros_bag(path: str | Path) -> bool:
    """True for what only this reader opens: a rosbag2 directory (with metadata.yaml), a ``.db3`` or ``.bag`` file, or an
    ``.mcap`` file that is not an aefabmap log (no ``aefabmap.log`` metadata). Our ros2-profile logs
    carry that metadata too, so they go to the MCAP log reader, which also reads their results."""
    p = Path(path)
    if p.is_dir():
        return (p / "metadata.yaml").is_file()  # a rosbag2 directory; other directories are rotated aefabmap logs
    if p.suffix in (".db3", ".bag"):
        return True
    if p.suffix == ".mcap" and p.is_file():
        try:
            return LOG_METADATA not in read_log_metadata(p)
        except LogError:
            return False  # not MCAP at all: let the MCAP reader say so
    return False


def rosbags_available() -> bool:
    try:
        import rosbags.highlevel  # noqa: F401
    except ImportError:
        return False
    return True


class RosBagReader:
    """Single-pass reader of the images of one topic of a ROS bag; the replay interface of
    McapLogReader (``frames()``, ``status``; no logged results, manifest, format or extraction version)."""

    format_version = None
    extraction_version = None
    manifest = None
    run_config = None

    def __init__(self, path: str | Path, *, image_topic: str | None = None) -> None:
        self.path = Path(path)
        if not self.path.exists():
            raise LogError(f"ROS bag {self.path} does not exist")
        if self.path.is_dir() and not (self.path / "metadata.yaml").is_file():
            raise LogError(f"{self.path} is a directory without metadata.yaml, not a rosbag2 bag")
        # The bag's reader opens its files plainly: a FIFO among them would block it for ever.
        for p in self.path.iterdir() if self.path.is_dir() else (self.path,):
            if not (p.is_file() or p.is_dir()):
                raise LogError(f"ROS bag {p} is not a regular file")
        if not rosbags_available():
            raise LogError(f"{self.path}: {INSTALL_HINT}")
        self.image_topic = image_topic
        self.results: list = []
        self.stats: list = []
        self.metadata: dict[str, dict] = {}
        self.status = ReadStatus(str(self.path))
        self._spent = False

    def frames(self) -> Iterator[LoggedImage]:
        if self._spent:
            raise LogError(f"{self.path}: a bag reader can be iterated only once")
        self._spent = True
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore

        try:
            reader = AnyReader([self.path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
            reader.open()
        except Exception as exc:  # rosbags raises several unrelated types for unreadable bags
            raise LogError(self._unreadable(exc)) from exc
        try:
            chosen = self._choose(reader.connections)
            ros1 = not reader.is2
            for conn, log_time, rawdata in reader.messages(connections=chosen):
                self.status.messages_read += 1
                image = self._decode(reader, conn, rawdata, ros1)
                if image is None:
                    continue
                self.status.images_read += 1
                yield LoggedImage(conn.topic, image.payload, image.encoding, image.stamp_ns or int(log_time),
                                  int(log_time), self.status.messages_read - 1)
        except LogError:
            raise
        except Exception as exc:  # noqa: BLE001 - a storage error mid-bag: stop there, like a truncated log
            self.status.truncated = True
            self.status.reason = f"{type(exc).__name__}: {exc}"[:200]
        finally:
            reader.close()

    def _unreadable(self, exc: Exception) -> str:
        """Why the bag does not open, in one line: an MCAP file whose records break off or are
        corrupt is a damaged MCAP log, whatever the bag reader's own error says."""
        if self.path.suffix == ".mcap" and self.path.is_file():
            status = ReadStatus(str(self.path))
            with open_log_file(self.path) as f:
                for _ in complete_records(f, status):
                    pass
            if status.truncated:
                return " ".join(f"{self.path} is a damaged MCAP log ({status.reason})".splitlines())
        return " ".join(f"cannot read ROS bag {self.path}: {type(exc).__name__}: {exc}"[:300].splitlines())

    def _choose(self, connections) -> list:
        images = [c for c in connections if c.msgtype in _IMAGE_TYPES]
        topics = list(dict.fromkeys(c.topic for c in images))
        if not topics:
            others = ", ".join(f"{c.topic} ({c.msgtype})" for c in connections) or "none"
            raise LogError(f"{self.path} has no sensor_msgs Image or CompressedImage topic (topics: {others})")
        if self.image_topic is None:
            if len(topics) > 1:
                raise LogError(f"{self.path} has several image topics, pick one with --topic: " + ", ".join(topics))
            topic = topics[0]
        elif self.image_topic in topics:
            topic = self.image_topic
        else:
            raise LogError(f"{self.path} has no image topic {self.image_topic}; image topics: " + ", ".join(topics))
        self.status.image_topic = topic
        self.status.ignored_image_topics = [t for t in topics if t != topic]
        return [c for c in images if c.topic == topic]

    def _decode(self, reader, conn, rawdata: bytes, ros1: bool):
        try:
            if not ros1:
                return DECODERS[conn.msgtype](rawdata)
            msg = reader.deserialize(rawdata, conn.msgtype)
            stamp = int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)
            if conn.msgtype == COMPRESSED_IMAGE_TYPE:
                return compressed_from_fields(stamp_ns=stamp, frame_id=msg.header.frame_id, fmt=msg.format,
                                              data=msg.data)
            return image_from_fields(stamp_ns=stamp, frame_id=msg.header.frame_id, encoding=msg.encoding,
                                     width=msg.width, height=msg.height, step=msg.step,
                                     is_bigendian=msg.is_bigendian, data=msg.data)
        except FrameError as exc:
            self.status.undecodable_messages += 1
            self.status.invalid_messages += 1
            self.status.last_invalid = f"{exc.reason}: {exc}"[:200]
            return None
        except Exception as exc:  # noqa: BLE001 - ROS 1 deserializer on malformed bytes
            self.status.undecodable_messages += 1
            self.status.invalid_messages += 1
            self.status.last_invalid = f"{type(exc).__name__}: {exc}"[:200]
            return None


def open_replay_source(sources, *, image_topic: str | None = None):
    """The reader for a replay source.

    sources: one path, or several (files, a directory of rotated logs, globs). One ROS bag (a
    rosbag2 directory, ``.db3``, ``.bag``, or an ``.mcap`` that is not an aefabmap log) goes to
    RosBagReader when rosbags is installed (without it a ROS 2 ``.mcap`` bag still goes to the
    MCAP reader); aefabmap logs go to the log-set reader, which reads rotated files as one run.
    """
    from aefabmap_runtime.adapters.log_set import open_log_reader

    single = sources if isinstance(sources, (str, Path)) else (sources[0] if len(sources) == 1 else None)
    if single is not None and is_ros_bag(single) and (Path(single).suffix != ".mcap" or rosbags_available()):
        return RosBagReader(Path(single), image_topic=image_topic)
    return open_log_reader(sources, image_topic=image_topic)
