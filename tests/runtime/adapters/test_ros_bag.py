"""Any ROS bag through `aefabmap replay` (runtime/aefabmap_runtime/adapters/ros_bag.py), bags written by rosbags.

Each bag has, like a real robot's, a depth-like mono16 topic registered first, a non-image
topic, and the colour camera; replaying the colour topic must give exactly the results of
the same frames run through the image-folder path.
"""

from __future__ import annotations

import json
import sys

import cv2
import numpy as np
import pytest

from aefabmap_runtime.errors import LogError
from aefabmap_runtime.adapters.frame_loop import FrameLoop
from aefabmap_runtime.adapters.image_folder import list_images
from aefabmap_runtime.adapters.replay import (
    NONDETERMINISTIC_FIELDS,
    compare_results,
    replay,
)
from aefabmap_runtime.adapters.ros_bag import INSTALL_HINT, RosBagReader

from .stream_fakes import FakeDetector, sample_images

pytest.importorskip("rosbags.rosbag2")
from rosbags.rosbag1 import Writer as Ros1Writer
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore
from tests.conftest import cli_args

STAMP0 = 1_700_000_000_000_000_000
COLOUR = "/camera/color/image_raw"
DEPTH = "/camera/depth/image_raw"


def _header(T, stamp_ns: int):
    stamp = T["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)
    Header = T["std_msgs/msg/Header"]
    extra = {"seq": 0} if "seq" in Header.__dataclass_fields__ else {}  # ROS 1 headers are numbered
    return Header(stamp=stamp, frame_id="camera", **extra)


def _raw(T, stamp_ns: int, img: np.ndarray, encoding: str):
    h, w = img.shape[:2]
    data = np.ascontiguousarray(img).view(np.uint8).reshape(-1)
    return T["sensor_msgs/msg/Image"](header=_header(T, stamp_ns), height=h, width=w, encoding=encoding,
                                      is_bigendian=0, step=data.size // h, data=data)


def write_bag(writer, ts, colour_frames, stamps) -> None:
    """colour_frames: ("jpeg", file bytes) or ("bgr8", (H, W, 3) array) per frame."""
    T = ts.types
    depth = writer.add_connection(DEPTH, "sensor_msgs/msg/Image", typestore=ts)
    chatter = writer.add_connection("/chatter", "std_msgs/msg/String", typestore=ts)
    kind = colour_frames[0][0]
    colour_type = "sensor_msgs/msg/CompressedImage" if kind == "jpeg" else "sensor_msgs/msg/Image"
    colour = writer.add_connection(COLOUR, colour_type, typestore=ts)
    ser = ts.serialize_cdr if isinstance(writer, Writer) else ts.serialize_ros1
    for i, ((kind, frame), stamp) in enumerate(zip(colour_frames, stamps)):
        depth_img = np.full((48, 64), 1000 + i, np.uint16)
        writer.write(depth, stamp - 1, bytes(ser(_raw(T, stamp - 1, depth_img, "mono16"), "sensor_msgs/msg/Image")))
        writer.write(chatter, stamp, bytes(ser(T["std_msgs/msg/String"](data=f"frame {i}"), "std_msgs/msg/String")))
        if kind == "jpeg":
            msg = T["sensor_msgs/msg/CompressedImage"](header=_header(T, stamp), format="jpeg",
                                                       data=np.frombuffer(frame, np.uint8))
        else:
            msg = _raw(T, stamp, frame, "bgr8")
        writer.write(colour, stamp, bytes(ser(msg, colour_type)))


def write_ros2(path, storage: str, colour_frames, stamps):
    ts = get_typestore(Stores.ROS2_HUMBLE)
    plugin = StoragePlugin.SQLITE3 if storage == "sqlite3" else StoragePlugin.MCAP
    with Writer(path, version=9, storage_plugin=plugin) as writer:
        write_bag(writer, ts, colour_frames, stamps)
    return path


def _stripped(docs):
    return [{k: v for k, v in d.items() if k not in NONDETERMINISTIC_FIELDS} for d in docs]


@pytest.mark.slow
@pytest.mark.data
def test_lip6_bags_replay_like_the_image_folder(lip6, tmp_path):
    from aefabmap_runtime.adapters.bundle_reader import load_detector
    from aefabmap_runtime.core.detector import DetectorConfig
    from tests.conftest import make_synthetic_bundle

    files = list_images(lip6)[:100]
    stamps = [STAMP0 + i * 100_000_000 for i in range(len(files))]
    bundle = make_synthetic_bundle(tmp_path / "bundle")
    reference = FrameLoop(load_detector(bundle, DetectorConfig()))
    expected = [reference.step_file(f, s).result.to_dict() for f, s in zip(files, stamps)]
    frames = [("jpeg", f.read_bytes()) for f in files]
    for storage in ("sqlite3", "mcap"):
        bag = write_ros2(tmp_path / f"lip6_{storage}", storage, frames, stamps)
        with pytest.raises(LogError) as info:  # several image topics, none chosen: listed
            replay(FakeDetector(), bag)
        assert DEPTH in str(info.value) and COLOUR in str(info.value)
        seen = []
        summary = replay(load_detector(bundle, DetectorConfig()), bag, image_topic=COLOUR, on_result=seen.append)
        assert summary.frames_processed == len(files) and summary.status.ignored_image_topics == [DEPTH]
        report = compare_results(expected, seen)
        assert report.ok and report.compared == len(files), report.describe()
        assert _stripped(seen) == _stripped(expected)


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_synthetic_bags_replay_like_the_frames_themselves(tmp_path, storage):
    grays = sample_images(12, size=(96, 72))
    colour = [cv2.cvtColor(g, cv2.COLOR_GRAY2BGR) for g in grays]
    colour[3][10:20, 10:20] = (0, 0, 255)  # some real colour
    stamps = [STAMP0 + i * 50_000_000 for i in range(len(colour))]
    bag = write_ros2(tmp_path / f"bag_{storage}", storage, [("bgr8", c) for c in colour], stamps)
    reference = FrameLoop(FakeDetector())
    expected = [reference.step_image(cv2.cvtColor(c, cv2.COLOR_BGR2GRAY), s).result.to_dict()
                for c, s in zip(colour, stamps)]
    seen = []
    summary = replay(FakeDetector(), bag, image_topic=COLOUR, on_result=seen.append)
    assert summary.frames_processed == 12 and sum(summary.bad.values()) == 0
    assert _stripped(seen) == _stripped(expected)
    storage_file = next(bag.glob("*.db3" if storage == "sqlite3" else "*.mcap"))
    seen_file = []
    replay(FakeDetector(), storage_file, image_topic=COLOUR, on_result=seen_file.append)  # bare file, no yaml
    assert _stripped(seen_file) == _stripped(expected)
    depth = replay(FakeDetector(), bag, image_topic=DEPTH)  # mono16 decodes too (high byte)
    assert depth.frames_processed == 12


def test_ros1_bag_replays(tmp_path):
    ts = get_typestore(Stores.ROS1_NOETIC)
    grays = sample_images(6, size=(96, 72))
    colour = [cv2.cvtColor(g, cv2.COLOR_GRAY2BGR) for g in grays]
    stamps = [STAMP0 + i * 50_000_000 for i in range(len(colour))]
    path = tmp_path / "robot.bag"
    with Ros1Writer(path) as writer:
        write_bag(writer, ts, [("bgr8", c) for c in colour], stamps)
    seen = []
    summary = replay(FakeDetector(), path, image_topic=COLOUR, on_result=seen.append)
    assert summary.frames_processed == 6 and [d["stamp_ns"] for d in seen] == stamps


def test_unusable_bags_fail_with_a_reason(tmp_path, monkeypatch, capsys):
    import aefabmap_runtime.adapters.bundle_reader as bundle_reader_mod
    from aefabmap.cli import replay as cli_replay

    ts = get_typestore(Stores.ROS2_HUMBLE)
    only_text = tmp_path / "text"
    with Writer(only_text, version=9) as writer:
        conn = writer.add_connection("/chatter", "std_msgs/msg/String", typestore=ts)
        writer.write(conn, STAMP0, bytes(ts.serialize_cdr(ts.types["std_msgs/msg/String"](data="hi"),
                                                          "std_msgs/msg/String")))
    with pytest.raises(LogError, match="no sensor_msgs Image"):
        replay(FakeDetector(), only_text)
    empty_dir = tmp_path / "not_a_bag"
    empty_dir.mkdir()
    with pytest.raises(LogError, match="metadata.yaml"):
        RosBagReader(empty_dir)

    monkeypatch.setattr(bundle_reader_mod, "load_detector", lambda *a, **k: FakeDetector())
    colour = [cv2.cvtColor(g, cv2.COLOR_GRAY2BGR) for g in sample_images(4, size=(96, 72))]
    bag = write_ros2(tmp_path / "cli_bag", "sqlite3", [("bgr8", c) for c in colour],
                     [STAMP0 + i for i in range(4)])

    def run(log, topic=None) -> int:
        return cli_replay.main(cli_args("replay", *log, "--model", "fake", *(("--topic", topic) if topic else ())))

    assert run(log=[str(bag)], topic=COLOUR) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["frames_processed"] == 4
    assert run(log=[str(bag)]) == LogError.exit_code  # two image topics, none given
    assert run(log=[str(only_text)]) == LogError.exit_code
    assert run(log=[str(bag)], topic="/nope") == LogError.exit_code

    # Without rosbags, one line says how to get it.
    monkeypatch.setitem(sys.modules, "rosbags.highlevel", None)
    with pytest.raises(LogError) as info:
        RosBagReader(bag)
    assert INSTALL_HINT in str(info.value) and "\n" not in str(info.value)
