"""A --ros-topic nobody publishes (runtime/aefabmap_runtime/adapters/ros_topic_check.py): one warning in the
log naming the image topics that are published, and the status says so until the topic comes.

The cameras are ROS 2 nodes as rmw_zenoh makes them (its docs/design.md and liveliness_utils.cpp),
written here by hand: a node token (NN), one publisher token (MP) per topic with its type, type
hash and the sensor-data QoS, and their data on ``<domain>/<topic>/<type>/<hash>`` with rmw_zenoh's
attachment (zenoh-ext's serializer), CDR by rosbags; all through a real Zenoh router on loopback.
"""

from __future__ import annotations

import logging
import threading
import time

import pytest
import zenoh

from aefabmap_runtime.adapters.health import find_runtimes, query_status
from aefabmap_runtime.adapters.rmw_zenoh import COMPRESSED_IMAGE_RIHS01, IMAGE_RIHS01, STRING_RIHS01, RosOptions
from aefabmap_runtime.adapters.ros_topic_check import CHECK_AFTER_S
from aefabmap_runtime.adapters.zenoh_transport import build_zenoh_config

from .stream_fakes import FakeDetector, NodeThread, sample_images
from .test_rmw_zenoh import STAMP0, Router, rmw_attachment, ros_image

rosbags_typesys = pytest.importorskip("rosbags.typesys")
pytestmark = pytest.mark.timeout(90)

IMAGE, COMPRESSED, STRING = "sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage", "std_msgs/msg/String"
#: type -> (DDS-mangled name, RIHS01 hash) as a Jazzy node puts them in its keys and tokens.
WIRE = {IMAGE: ("sensor_msgs::msg::dds_::Image_", IMAGE_RIHS01),
        COMPRESSED: ("sensor_msgs::msg::dds_::CompressedImage_", COMPRESSED_IMAGE_RIHS01),
        STRING: ("std_msgs::msg::dds_::String_", STRING_RIHS01)}
#: rmw_zenoh's QoS chunk of a sensor-data publisher: best effort (2), keep last 5, the rest default.
SENSOR_DATA_QOS = "2::,5:,:,:,,"


class RmwCamera:
    """A ROS 2 node publishing ``topics`` (topic -> type) in ``domain`` as rmw_zenoh does."""

    def __init__(self, session: zenoh.Session, topics: dict[str, str], *, domain: int = 0, node: str = "camera"):
        zid = session.info.zid()
        self.tokens = [session.liveliness().declare_token(f"@ros2_lv/{domain}/{zid}/0/0/NN/%/%/{node}")]
        self.pubs, self.seq = {}, 0
        for entity, (topic, ros_type) in enumerate(topics.items(), start=10):
            mangled, type_hash = WIRE[ros_type]
            self.tokens.append(session.liveliness().declare_token(
                f"@ros2_lv/{domain}/{zid}/0/{entity}/MP/%/%/{node}/{topic.replace('/', '%')}/{mangled}/{type_hash}/"
                f"{SENSOR_DATA_QOS}"))
            self.pubs[topic] = session.declare_publisher(f"{domain}/{topic.strip('/')}/{mangled}/{type_hash}",
                                                         congestion_control=zenoh.CongestionControl.BLOCK)

    def put(self, topic: str, cdr: bytes) -> None:
        self.seq += 1
        self.pubs[topic].put(cdr, attachment=rmw_attachment(self.seq, STAMP0 + self.seq))

    def close(self) -> None:
        for entity in [*self.pubs.values(), *self.tokens]:
            entity.undeclare()


class RosLog(logging.Handler):
    """The ``aefabmap.ros`` records from INFO up, each with the monotonic time it came."""

    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.logger = logging.getLogger("aefabmap.ros")
        self.saved_level = self.logger.level
        self.logger.setLevel(logging.INFO)
        self.records: list[tuple[float, int, str]] = []
        self.cond = threading.Condition()
        self.logger.addHandler(self)

    def emit(self, record: logging.LogRecord) -> None:
        with self.cond:
            self.records.append((time.monotonic(), record.levelno, record.getMessage()))
            self.cond.notify_all()

    def wait(self, predicate, timeout_s: float) -> list[tuple[float, int, str]]:
        with self.cond:
            assert self.cond.wait_for(lambda: predicate(self.records), timeout_s), self.records
            return list(self.records)

    def warnings(self) -> list[str]:
        with self.cond:
            return [m for _, level, m in self.records if level == logging.WARNING]

    def close(self) -> None:
        self.logger.removeHandler(self)
        self.logger.setLevel(self.saved_level)
        super().close()


def node_status(session: zenoh.Session, predicate, timeout_s: float = 20.0):
    """The node's StatusMessage once ``predicate(status)`` holds (queried until timeout_s)."""
    deadline, pause, status = time.monotonic() + timeout_s, threading.Event(), None
    while time.monotonic() < deadline:
        zids = find_runtimes(session, 2.0)
        answers = [s for s in query_status(session, zids, 2.0).values() if not isinstance(s, str)] if zids else []
        if answers:
            status = answers[0]
            if predicate(status):
                return status
        pause.wait(0.05)
    raise AssertionError(f"the status never matched: {status}")


def test_a_topic_nobody_publishes_is_warned_once_with_the_image_topics_that_are(tmp_path):
    ts = rosbags_typesys.get_typestore(rosbags_typesys.Stores.ROS2_JAZZY)
    logged = RosLog()
    router = Router()
    try:
        with (
            zenoh.open(build_zenoh_config(router.ros_peer())) as ros,
            zenoh.open(build_zenoh_config(router.ros_peer())) as other_domain,
        ):
            camera = RmwCamera(ros, {"/camera/image_raw": IMAGE, "/camera/image_raw/compressed": COMPRESSED,
                                     "/chatter": STRING})
            front = RmwCamera(other_domain, {"/front/image": IMAGE}, domain=3, node="front")
            with NodeThread(detector=FakeDetector(), session_config=router.ros_peer(), key="unused",
                            mcap_path=tmp_path / "wrong.mcap", stats_period_s=0.1,
                            ros=RosOptions(topic="/camera/image")) as node:
                ready = time.monotonic()
                records = logged.wait(lambda rs: any(level == logging.WARNING for _, level, _ in rs), 15)
                when, _, text = next(r for r in records if r[1] == logging.WARNING)
                # Said within the stated bound, and not before it.
                assert CHECK_AFTER_S - 0.5 <= when - ready <= CHECK_AFTER_S + 1.5, when - ready
                status = node_status(ros, lambda s: s.uptime_s >= CHECK_AFTER_S + 2.5)
                assert status.ros_topic_published is False
                assert status.ros_image_topics == ["/camera/image_raw (sensor_msgs/msg/Image)",
                                                   "/camera/image_raw/compressed (sensor_msgs/msg/CompressedImage)",
                                                   "/front/image (sensor_msgs/msg/Image) in domain 3"]
                assert status.warnings == [text]
                assert logged.warnings() == [text]  # one warning, however many stats and polls went by
                # The camera comes on the topic asked for: its images are processed, the warning goes.
                late = RmwCamera(ros, {"/camera/image": IMAGE}, node="late")
                gray = sample_images(1, size=(160, 120))[0]
                late.put("/camera/image", ros_image(ts, gray, "mono8", STAMP0))
                status = node_status(ros, lambda s: s.frames_processed == 1)
                assert status.ros_topic_published is True and status.ros_image_topics == [] and status.warnings == []
                logged.wait(lambda rs: any("/camera/image is published now" in m for _, _, m in rs), 10)
                late.close()
                node.finish()
            camera.close()
            front.close()
    finally:
        router.close()
        logged.close()
    assert "/camera/image has no publisher in domain 0" in text
    for named in ("/camera/image_raw (sensor_msgs/msg/Image)",
                  "/camera/image_raw/compressed (sensor_msgs/msg/CompressedImage)",
                  "/front/image (sensor_msgs/msg/Image) in domain 3", "--ros-topic"):
        assert named in text, text
    assert "/chatter" not in text
    assert logged.warnings() == [text]


def test_a_published_topic_is_not_warned_before_its_first_image(tmp_path):
    """The camera's publisher token is enough: no image has come yet, nothing is warned."""
    logged = RosLog()
    router = Router()
    try:
        with zenoh.open(build_zenoh_config(router.ros_peer())) as ros:
            camera = RmwCamera(ros, {"/camera/image_raw": IMAGE})
            with NodeThread(detector=FakeDetector(), session_config=router.ros_peer(), key="unused",
                            mcap_path=tmp_path / "idle.mcap", stats_period_s=0.1,
                            ros=RosOptions(topic="/camera/image_raw")) as node:
                status = node_status(ros, lambda s: s.uptime_s >= CHECK_AFTER_S + 1.5)
                node.finish()
            camera.close()
    finally:
        router.close()
        logged.close()
    assert status.ros_topic_published is True and status.warnings == [] and status.frames_received == 0
    assert logged.warnings() == []
