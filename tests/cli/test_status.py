"""``aefabmap status`` as a subprocess against a real node on loopback (aefabmap/cli/status.py)."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from aefabmap_runtime.core.records.messages import StatusMessage
from aefabmap_runtime.tools.node_process import free_tcp_port
from aefabmap_runtime.tools.publisher import array_source, publish_frames
from tests.runtime.adapters.stream_fakes import (
    FakeDetector,
    NodeThread,
    sample_images,
    session_pair,
)

pytestmark = pytest.mark.timeout(90)
KEY = "robot/camera/image"


def _status(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "aefabmap.cli.main", "status", *args],
                          check=False, capture_output=True, text=True, timeout=60)


def test_status_finds_a_running_node(tmp_path):
    listen, connect = session_pair()
    (endpoint,) = connect.connect
    with NodeThread(FakeDetector(), listen, key=KEY, mcap_path=tmp_path / "run.mcap", queue_size=16) as node:
        pub = publish_frames(connect, KEY, array_source(sample_images(3), "jpeg"), rate_hz=100,
                             wait_for_subscriber_s=10)
        assert pub.published == 3
        machine = _status("--connect", endpoint, "--timeout", "5", "--json")
        human = _status("--connect", endpoint, "--timeout", "5")
        node.finish()
    assert machine.returncode == 0, machine.stderr
    (doc,) = json.loads(machine.stdout)
    status = StatusMessage.from_json(doc)
    assert status.results_key == "robot/camera/lcd" and status.frames_received <= 3
    assert human.returncode == 0, human.stderr
    assert human.stdout.count("\n") == 1 and status.zid in human.stdout and "robot/camera/lcd" in human.stdout


def test_status_without_a_node_says_so():
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    done = _status("--connect", endpoint, "--timeout", "1")
    assert done.returncode == 1, done.stderr
    assert done.stdout.strip() == f"no aefabmap runtime found on {endpoint}"


def test_status_refuses_a_bad_endpoint():
    done = _status("--connect", "nonsense", "--timeout", "1")
    assert done.returncode == 2 and "endpoint" in done.stderr and "Traceback" not in done.stderr


def test_status_prints_a_ros_topic_nobody_publishes_and_exits_1(tmp_path):
    """A node reading a ROS 2 topic that has no publisher, while a camera publishes another one
    (rmw_zenoh's tokens): `status` prints the warning, naming the camera's topic, and exits 1."""
    import zenoh

    from aefabmap_runtime.adapters.rmw_zenoh import RosOptions
    from aefabmap_runtime.adapters.zenoh_transport import build_zenoh_config
    from tests.runtime.adapters.test_rmw_zenoh import Router
    from tests.runtime.adapters.test_ros_topic_check import IMAGE, RmwCamera, node_status

    router = Router()
    try:
        with zenoh.open(build_zenoh_config(router.ros_peer())) as ros:
            camera = RmwCamera(ros, {"/camera/image_raw": IMAGE})
            with NodeThread(FakeDetector(), router.ros_peer(), key="unused", mcap_path=tmp_path / "ros.mcap",
                            ros=RosOptions(topic="/camera/image")) as node:
                node_status(ros, lambda s: s.warnings)
                human = _status("--connect", router.endpoint, "--timeout", "5")
                machine = _status("--connect", router.endpoint, "--timeout", "5", "--json")
                node.finish()
            camera.close()
    finally:
        router.close()
    assert human.returncode == 1, human.stderr
    assert len(human.stdout.splitlines()) == 2, human.stdout
    node_line, warning = human.stdout.splitlines()
    zid = node_line.split()[0]
    assert warning.startswith(f"{zid}  warning: ROS 2 topic /camera/image has no publisher")
    assert "/camera/image_raw (sensor_msgs/msg/Image)" in warning
    assert machine.returncode == 1
    (doc,) = json.loads(machine.stdout)
    assert doc["ros_topic_published"] is False
    assert doc["ros_image_topics"] == ["/camera/image_raw (sensor_msgs/msg/Image)"]
