"""ROS 2 over DDS through zenoh-bridge-ros2dds (runtime/aefabmap_runtime/adapters/ros2dds_bridge.py).

The bridge's side is written from its README, DEFAULT_CONFIG.json5 and sources
(eclipse-zenoh/zenoh-plugin-ros2dds), not from the adapter: a DDS topic ``/camera/image_raw`` is the
key ``camera/image_raw`` (``bot1/camera/image_raw`` behind a bridge given the namespace ``/bot1``),
the payload is the DDS sample's CDR as it is (rosbags' serializer here) with no attachment, and each
DDS publisher the bridge routes is announced by the liveliness token
``@/<zid>/@ros2_lv/MP/<key, / as §>/<type, / as §>/<qos>``. A Zenoh router on loopback stands in
for the bridge, which runs as one.
"""

from __future__ import annotations

import json
import threading

import pytest
import zenoh

from aefabmap_runtime.adapters.rmw_zenoh import RosOptions
from aefabmap_runtime.adapters.ros_topic_check import CHECK_AFTER_S
from aefabmap_runtime.adapters.zenoh_transport import build_zenoh_config
from tests.conftest import cli_args

from .stream_fakes import FakeDetector, JsonCollector, NodeThread, sample_images
from .test_rmw_zenoh import STAMP0, Router, ros_compressed, ros_image, run_cli_while
from .test_ros_topic_check import RosLog, node_status

rosbags_typesys = pytest.importorskip("rosbags.typesys")
pytestmark = pytest.mark.timeout(90)

IMAGE, COMPRESSED = "sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage"


@pytest.fixture(scope="module")
def typestore():
    return rosbags_typesys.get_typestore(rosbags_typesys.Stores.ROS2_JAZZY)


def bridge_key(namespace: str, topic: str) -> str:
    """The bridge's key of a ROS name (ros2_name_to_key_expr): the name without its leading
    slash, after the bridge's namespace without its own."""
    return f"{namespace.strip('/')}/{topic[1:]}" if namespace.strip("/") else topic[1:]


class BridgeCamera:
    """A DDS camera as zenoh-bridge-ros2dds shows it on Zenoh: the route's liveliness token (keyless
    topic, best effort, volatile, keep last 5 in CycloneDDS's numbering) and the samples."""

    def __init__(self, session: zenoh.Session, topic: str, ros_type: str, namespace: str = "/") -> None:
        self.key = bridge_key(namespace, topic)
        zid = session.info.zid()
        self.token = session.liveliness().declare_token(
            f"@/{zid}/@ros2_lv/MP/{self.key.replace('/', '§')}/{ros_type.replace('/', '§')}/:0:0:0,5")
        self.pub = session.declare_publisher(self.key, congestion_control=zenoh.CongestionControl.BLOCK)

    def wait_for_subscriber(self, timeout_s: float = 10.0) -> None:
        pause = threading.Event()
        for _ in range(int(timeout_s / 0.05)):
            if self.pub.matching_status.matching:
                return
            pause.wait(0.05)
        raise AssertionError(f"nobody subscribed to {self.key}")

    def close(self) -> None:
        self.pub.undeclare()
        self.token.undeclare()


class CdrCollector:
    """The CDR samples of one key, decoded by rosbags as ``ros_type``."""

    def __init__(self, session: zenoh.Session, key: str, ts, ros_type: str) -> None:
        self.msgs: list = []
        self.cond = threading.Condition()

        def on_sample(sample) -> None:
            with self.cond:
                self.msgs.append(ts.deserialize_cdr(sample.payload.to_bytes(), ros_type))
                self.cond.notify_all()

        self.sub = session.declare_subscriber(key, on_sample)

    def wait(self, predicate, timeout_s: float = 20.0) -> list:
        with self.cond:
            assert self.cond.wait_for(lambda: predicate(self.msgs), timeout_s), f"{len(self.msgs)} messages"
            return list(self.msgs)


@pytest.mark.parametrize("namespace", ["/", "/bot1"])
def test_images_through_the_bridge_give_results_on_its_keys(tmp_path, typestore, namespace):
    images = sample_images(3, size=(160, 120))
    stamps = [STAMP0 + 10**9 * (i + 1) + 7 for i in range(3)]
    text = bytes(typestore.serialize_cdr(typestore.types["std_msgs/msg/String"](data="hi"), "std_msgs/msg/String"))
    router = Router()
    try:
        with (
            NodeThread(detector=FakeDetector(), session_config=router.ros_peer(), key="unused",
                       mcap_path=tmp_path / "bridge.mcap", queue_size=16, stats_period_s=0.2,
                       ros=RosOptions(topic="/camera/image_raw", bridge=namespace)) as node,
            zenoh.open(build_zenoh_config(router.ros_peer())) as bridge,
        ):
            results = CdrCollector(bridge, bridge_key(namespace, "/lcd/result"), typestore, "std_msgs/msg/String")
            diagnostics = CdrCollector(bridge, bridge_key(namespace, "/diagnostics"), typestore,
                                       "diagnostic_msgs/msg/DiagnosticArray")
            plain = JsonCollector(bridge, bridge_key(namespace, "/camera/lcd"))
            camera = BridgeCamera(bridge, "/camera/image_raw", IMAGE, namespace)
            camera.wait_for_subscriber()
            camera.pub.put(ros_image(typestore, images[0], "mono8", stamps[0]))
            camera.pub.put(text)  # not an image: refused, counted
            camera.pub.put(ros_image(typestore, images[1], "bgr8", stamps[1]))
            camera.pub.put(ros_compressed(typestore, images[2], stamps[2]))
            docs = [json.loads(m.data) for m in results.wait(lambda ms: len(ms) >= 3)]
            plain.wait_for(lambda d: d["sequence"] == 2, timeout_s=20)
            diags = diagnostics.wait(lambda ms: any(kv.key == "frames_received" and kv.value == "4"
                                                    for m in ms for s in m.status for kv in s.values))
            status = node_status(bridge, lambda s: s.frames_processed == 3)
            summary = node.finish()
            camera.close()
            plain.close()
    finally:
        router.close()
    assert [d["sequence"] for d in docs] == [0, 1, 2]
    assert [d["stamp_ns"] for d in docs] == stamps  # the header stamps
    assert all(d.get("frame_seq") is None for d in docs)  # the bridge attaches no sequence number
    assert summary.frames_processed == 3 and summary.dropped == 0
    assert {k: v for k, v in summary.bad.items() if v} == {"corrupt": 1}  # no bad_attachment: none is expected
    assert diags[-1].status[0].name == "aefabmap: aefabmap"
    assert status.ros_topic_published is True and status.warnings == []


def test_a_topic_the_bridge_does_not_route_is_warned_with_the_ones_it_does(tmp_path):
    """The robot's bridge (namespace /bot1) routes /camera/image_raw, another bridge (no namespace)
    /front/image; a node asking the robot for /camera/image is told of both, once."""
    logged = RosLog()
    router = Router()
    try:
        with (
            zenoh.open(build_zenoh_config(router.ros_peer())) as robot,
            zenoh.open(build_zenoh_config(router.ros_peer())) as other,
        ):
            camera = BridgeCamera(robot, "/camera/image_raw", IMAGE, "/bot1")
            front = BridgeCamera(other, "/front/image", COMPRESSED)
            with NodeThread(detector=FakeDetector(), session_config=router.ros_peer(), key="unused",
                            mcap_path=tmp_path / "wrong.mcap", stats_period_s=0.1,
                            ros=RosOptions(topic="/camera/image", bridge="/bot1")) as node:
                status = node_status(robot, lambda s: s.uptime_s >= CHECK_AFTER_S + 1.5)
                node.finish()
            camera.close()
            front.close()
    finally:
        router.close()
        logged.close()
    assert status.ros_topic_published is False
    assert status.ros_image_topics == ["/camera/image_raw (sensor_msgs/msg/Image)",
                                       "/front/image (sensor_msgs/msg/CompressedImage) in zenoh-bridge-ros2dds "
                                       "namespace /"]
    (text,) = status.warnings
    assert text.startswith("ROS 2 topic /camera/image has no publisher in zenoh-bridge-ros2dds namespace /bot1")
    assert logged.warnings() == [text]


def test_cli_ros_bridge_options(tmp_path, monkeypatch):
    from aefabmap.cli.main import main
    from aefabmap.cli.run import node_io

    base = ["run", "--model", str(tmp_path / "none"), "--mcap", str(tmp_path / "x.mcap")]
    io = node_io(cli_args(*base, "--ros-topic", "/camera/image_raw", "--ros-bridge"))
    assert io.ros.bridge == "/" and io.ros.image_key == "camera/image_raw"
    monkeypatch.setenv("ROS_DOMAIN_ID", "7")  # the bridge's business, not the node's
    io = node_io(cli_args(*base, "--ros-topic", "/camera/image_raw", "--ros-bridge", "/bot1"))
    assert io.ros.image_key == "bot1/camera/image_raw" and io.ros.default_results_key == "bot1/camera/lcd"
    for bad in (["--key", "robot/camera/image", "--ros-bridge"],  # a bridge needs a ROS topic
                ["--ros-topic", "/camera/image_raw", "--ros-bridge", "--ros-domain", "3"],
                ["--ros-topic", "/camera/image_raw", "--ros-bridge", "--ros-distro", "jazzy"],
                ["--ros-topic", "/camera/image_raw", "--ros-bridge", "bot 1"]):
        assert main([*base, *bad]) == 2, bad


def test_cli_run_ros_bridge_through_a_router(tmp_path, typestore, monkeypatch, capsys):
    """`aefabmap run --ros-topic /camera/image_raw --ros-bridge --connect <bridge>` end to end."""
    import aefabmap_runtime.adapters.bundle_reader as bundle_reader_mod
    from aefabmap_runtime.adapters.mcap_log import RUN_CONFIG_METADATA, McapLogReader

    monkeypatch.setattr(bundle_reader_mod, "load_detector", lambda *a, **k: FakeDetector())
    router = Router()
    args = cli_args("run", "--model", "fake", "--ros-topic", "/camera/image_raw", "--ros-bridge",
                    "--connect", router.endpoint, "--mcap", tmp_path / "cli_bridge.mcap", "--queue", "4")

    def drive() -> None:
        with zenoh.open(build_zenoh_config(router.ros_peer())) as bridge:
            results = CdrCollector(bridge, "lcd/result", typestore, "std_msgs/msg/String")
            camera = BridgeCamera(bridge, "/camera/image_raw", IMAGE)
            camera.wait_for_subscriber(20)
            for i, img in enumerate(sample_images(2, size=(96, 72))):
                camera.pub.put(ros_image(typestore, img, "mono8", STAMP0 + i))
            assert [json.loads(m.data)["sequence"] for m in results.wait(lambda ms: len(ms) >= 2)] == [0, 1]
            camera.close()

    summary = run_cli_while(drive, args, router, capsys)
    assert summary["frames_processed"] == 2 and summary["result_key"] == "camera/lcd"
    reader = McapLogReader(tmp_path / "cli_bridge.mcap")
    assert len(list(reader.frames())) == 2
    ros = reader.metadata[RUN_CONFIG_METADATA]["ros"]
    assert ros["bridge"] == "/" and ros["domain"] is None and ros["topic"] == "/camera/image_raw"
