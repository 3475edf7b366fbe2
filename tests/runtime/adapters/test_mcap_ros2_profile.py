"""MCAP logs in the ros2 profile (``--mcap-profile ros2``): every message read back by rosbags'
AnyReader and mcap-ros2-support, replayed and checked by us; rotated, repaired and hostile files;
what rosbag2 writes besides the messages (QoS per channel, the ``rosbag2`` metadata record) read
as rosbag2 and rosbags read it; /diagnostics logged as published."""

from __future__ import annotations

import json
import logging
from collections import defaultdict
from pathlib import Path

import cv2
import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer

from aefabmap_runtime.adapters.frames import encode_frame
from aefabmap_runtime.adapters.log_repair import repair_log
from aefabmap_runtime.adapters.log_set import log_files
from aefabmap_runtime.adapters.mcap_log import (
    LOG_FORMAT_VERSION,
    LOG_METADATA,
    MANIFEST_METADATA,
    MESSAGE_KIND_KEY,
    ROS2_IMAGE_TOPIC,
    RUN_CONFIG_METADATA,
    McapLogConfig,
    McapLogReader,
    McapLogWriter,
)
from aefabmap_runtime.adapters.replay import replay
from aefabmap_runtime.adapters.ros_cdr import (
    COMPRESSED_IMAGE_MSGDEF,
    COMPRESSED_IMAGE_TYPE,
    DIAGNOSTIC_ARRAY_MSGDEF,
    DIAGNOSTIC_ARRAY_TYPE,
    STRING_MSGDEF,
    STRING_TYPE,
)
from aefabmap_runtime.adapters.rotating_log import LogRotationConfig, RotatingLog
from aefabmap_runtime.core.records.messages import FrameResult

from .stream_fakes import (
    CLI,
    FakeDetector,
    record_live_log,
    run_node_process,
    sample_images,
)
from tests.conftest import cli_args, make_synthetic_bundle

pytest.importorskip("rosbags.highlevel")  # a test/dev dependency, never imported by the runtime
pytestmark = pytest.mark.timeout(120)

ROS2 = McapLogConfig(profile="ros2")
TYPES = {ROS2_IMAGE_TOPIC: COMPRESSED_IMAGE_TYPE, "/lcd/result": STRING_TYPE, "/lcd/stats": STRING_TYPE,
         "/diagnostics": DIAGNOSTIC_ARRAY_TYPE}
STAMP0 = 1_700_000_000_000_000_000


def rosbags_messages(path: Path) -> tuple[dict[str, str], dict[str, list]]:
    """({topic: type}, {topic: [deserialised message]}) of every connection, read by rosbags' AnyReader."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    out: dict[str, list] = defaultdict(list)
    with AnyReader([Path(path)], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        for conn, _, raw in reader.messages():
            out[conn.topic].append(reader.deserialize(raw, conn.msgtype))
    return types, dict(out)


def mcap_ros2_decoded(path: Path) -> int:
    """Messages decoded by mcap-ros2-support (the ROS 2 decoder of the MCAP tooling Foxglove
    builds on); it raises on any message it cannot decode."""
    from mcap_ros2.decoder import DecoderFactory

    with open(path, "rb") as f:
        return sum(1 for _ in make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages())


def file_layout(path: Path) -> tuple[str, set[str], set[str], set[str]]:
    """(header profile, schema encodings, message encodings, metadata names) of an MCAP file."""
    with open(path, "rb") as f:
        reader = make_reader(f)
        profile = reader.get_header().profile
        summary = reader.get_summary()
        names = {m.name for m in reader.iter_metadata()}
    return (profile, {s.encoding for s in summary.schemas.values()},
            {c.message_encoding for c in summary.channels.values()}, names)


def stamp_ns(msg) -> int:
    return int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)


@pytest.fixture(scope="module")
def ros2_run(tmp_path_factory):
    """A live node's ros2-profile log: 16 frames, 8 jpeg then 8 raw mono8 (logged as png)."""
    path = tmp_path_factory.mktemp("ros2") / "run.mcap"
    summary, images = record_live_log(path, stats_period_s=0.2, log_config=ROS2, run_config={"model": "fake"})
    assert summary.frames_processed == 16 and summary.images_logged == 16
    return path, images


def test_rosbags_and_mcap_ros2_read_every_message_of_a_ros2_profile_run(ros2_run):
    path, images = ros2_run
    profile, schema_encodings, message_encodings, metadata = file_layout(path)
    assert profile == "ros2" and schema_encodings == {"ros2msg"} and message_encodings == {"cdr"}
    assert {LOG_METADATA, MANIFEST_METADATA, RUN_CONFIG_METADATA} <= metadata  # what the replay needs

    types, messages = rosbags_messages(path)
    assert types == TYPES
    frames, results = messages[ROS2_IMAGE_TOPIC], [json.loads(m.data) for m in messages["/lcd/result"]]
    stats = [json.loads(m.data) for m in messages["/lcd/stats"]]
    assert len(frames) == 16 and [r["sequence"] for r in results] == list(range(16))
    assert stats and stats[-1]["frames_processed"] == 16
    assert [m.format for m in frames] == ["jpeg"] * 8 + ["png"] * 8
    assert {m.header.frame_id for m in frames} == {"camera"}
    assert [stamp_ns(m) for m in frames] == [r["stamp_ns"] for r in results]  # header stamp = capture stamp
    for m, img in zip(frames[8:], images[8:]):  # raw frames: lossless png
        assert np.array_equal(cv2.imdecode(np.asarray(m.data, np.uint8), cv2.IMREAD_UNCHANGED), img)
    assert mcap_ros2_decoded(path) == sum(len(v) for v in messages.values())


def test_replay_check_of_a_ros2_profile_run_passes_and_writes_either_profile(ros2_run, tmp_path):
    path, _ = ros2_run
    reader = McapLogReader(path)
    assert len(list(reader.frames())) == 16 and reader.status.profile == "ros2"
    assert reader.run_config["model"] == "fake" and reader.manifest["detector"] == "fake"

    summary = replay(FakeDetector(), path, check=True)
    assert summary.check.ok and summary.check.compared == 16, summary.check.describe()
    assert summary.status.image_topic == ROS2_IMAGE_TOPIC

    ros2_out = replay(FakeDetector(), path, check=True, out_path=tmp_path / "re.mcap", log_config=ROS2)
    assert ros2_out.check.ok
    types, messages = rosbags_messages(tmp_path / "re.mcap")
    assert types == TYPES and len(messages["/lcd/result"]) == 16 and len(messages["/lcd/stats"]) == 1
    assert len(messages["/diagnostics"]) == 1 and messages["/diagnostics"][0].status[0].name == "aefabmap"
    assert replay(FakeDetector(), tmp_path / "re.mcap", check=True).check.compared == 16

    plain = replay(FakeDetector(), path, out_path=tmp_path / "plain.mcap")  # back to the default layout
    assert file_layout(Path(plain.out_path))[:3] == ("", {"protobuf", "jsonschema"}, {"protobuf", "json"})
    assert replay(FakeDetector(), plain.out_path, check=True).check.ok


def test_the_message_definitions_are_rosbags_own():
    from rosbags.typesys import Stores, get_typestore

    for store in (Stores.ROS2_HUMBLE, Stores.ROS2_JAZZY):
        typestore = get_typestore(store)
        assert typestore.generate_msgdef(COMPRESSED_IMAGE_TYPE, ros_version=2)[0] == COMPRESSED_IMAGE_MSGDEF
        assert typestore.generate_msgdef(STRING_TYPE, ros_version=2)[0] == STRING_MSGDEF
        assert typestore.generate_msgdef(DIAGNOSTIC_ARRAY_TYPE, ros_version=2)[0] == DIAGNOSTIC_ARRAY_MSGDEF


def test_the_default_profile_keeps_its_layout(tmp_path):
    assert McapLogConfig().profile == "aefabmap" and McapLogConfig().image_topic == "/camera/image"
    assert McapLogConfig(profile="ros2", image_topic="/cam/compressed").image_topic == "/cam/compressed"
    path = tmp_path / "default.mcap"
    with McapLogWriter(path) as w:
        payload, enc = encode_frame(sample_images(1, size=(64, 48))[0], "jpeg")
        w.write_image(payload, enc, STAMP0, sequence=0)
        w.write_result(FakeDetector().process(sample_images(1, size=(64, 48))[0], STAMP0))
    assert file_layout(path)[:3] == ("", {"protobuf", "jsonschema"}, {"protobuf", "json"})
    assert McapLogReader(path).status.profile is None  # set while reading
    from aefabmap_runtime.errors import ConfigError

    with pytest.raises(ConfigError, match="profile"):
        McapLogConfig(profile="ros1")


def _write_frames(log, images, detector, fmt="png") -> None:
    for i, img in enumerate(images):
        payload, enc = encode_frame(img, fmt)
        result = detector.process(img, STAMP0 + i * 50_000_000)
        log.write_image(payload, enc, result.stamp_ns, sequence=result.sequence)
        log.write_result(result)


def test_a_rotated_ros2_log_set_is_valid_file_by_file_and_replays_as_one_run(tmp_path):
    rotation = LogRotationConfig(max_mb=0.05, summary_reserve_bytes=4096, images_min_free_mb=0.0,
                                 results_min_free_mb=0.0)
    images = sample_images(40, size=(96, 72))
    (tmp_path / "set").mkdir()  # a directory target: files lcd-...-0001.mcap, -0002, ...
    with RotatingLog(tmp_path / "set", ROS2, rotation, manifest=FakeDetector().manifest) as log:
        log.open()
        _write_frames(log, images, FakeDetector())
    files = log_files(tmp_path / "set")
    assert len(files) >= 3 and log.errors == 0
    seen = 0
    for f in files:
        assert file_layout(f)[:3] == ("ros2", {"ros2msg"}, {"cdr"})
        types, messages = rosbags_messages(f)
        assert set(types) <= set(TYPES) and len(messages[ROS2_IMAGE_TOPIC]) == len(messages["/lcd/result"])
        seen += len(messages[ROS2_IMAGE_TOPIC])
    assert seen == 40
    summary = replay(FakeDetector(), tmp_path / "set", check=True)
    assert summary.check.ok and summary.check.compared == 40, summary.check.describe()


def test_a_cut_ros2_log_is_repaired_into_a_ros2_file(tmp_path):
    whole = tmp_path / "whole.mcap"
    with McapLogWriter(whole, McapLogConfig(profile="ros2", chunk_size=4096), run_config={"key": "a/b"}) as w:
        _write_frames(w, sample_images(30, size=(96, 72)), FakeDetector())
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(whole.read_bytes()[: int(whole.stat().st_size * 0.7)])
    report = repair_log(cut, tmp_path / "fixed.mcap")
    assert report.truncated and report.messages > 0
    types, messages = rosbags_messages(tmp_path / "fixed.mcap")
    assert types == TYPES  # every channel (stats without messages) and its schema kept
    fixed = McapLogReader(tmp_path / "fixed.mcap")
    frames = list(fixed.frames())
    assert len(frames) == len(messages[ROS2_IMAGE_TOPIC]) and len(fixed.results) == len(messages["/lcd/result"])
    assert fixed.status.profile == "ros2" and fixed.run_config == {"key": "a/b"}


def _hostile_ros2_log(path: Path, images) -> None:
    """A ros2-profile log written by hand (CDR by rosbags): frame 2's image and frame 4's result
    are cut CDR."""
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_JAZZY)
    Header, Time = ts.types["std_msgs/msg/Header"], ts.types["builtin_interfaces/msg/Time"]
    Image, String = ts.types[COMPRESSED_IMAGE_TYPE], ts.types[STRING_TYPE]
    detector = FakeDetector()
    with open(path, "wb") as f:
        w = Writer(f)
        w.start(profile="ros2", library="hostile test")
        w.add_metadata(LOG_METADATA, {"format_version": LOG_FORMAT_VERSION, "image_topic": ROS2_IMAGE_TOPIC,
                                      "result_topic": "/lcd/result", "stats_topic": "/lcd/stats"})
        image_schema = w.register_schema(COMPRESSED_IMAGE_TYPE, "ros2msg", COMPRESSED_IMAGE_MSGDEF.encode())
        image = w.register_channel(ROS2_IMAGE_TOPIC, "cdr", image_schema)
        string_schema = w.register_schema(STRING_TYPE, "ros2msg", STRING_MSGDEF.encode())
        result = w.register_channel("/lcd/result", "cdr", string_schema, {MESSAGE_KIND_KEY: FrameResult.TITLE})
        for i, img in enumerate(images):
            payload, _ = encode_frame(img, "jpeg")
            stamp = STAMP0 + i * 50_000_000
            head = Header(Time(stamp // 10**9, stamp % 10**9), "camera")
            data = ts.serialize_cdr(Image(head, "jpeg", np.frombuffer(payload, np.uint8)), COMPRESSED_IMAGE_TYPE)
            w.add_message(image, stamp, data[:40] if i == 2 else data, stamp, i)
            text = ts.serialize_cdr(String(detector.process(img, stamp).to_json_bytes().decode()), STRING_TYPE)
            w.add_message(result, stamp, text[:-9] if i == 4 else text, stamp, i)
        w.finish()


def test_a_corrupt_cdr_image_is_counted_and_reported_in_one_line(tmp_path, caplog):
    from aefabmap.cli import replay as cli_replay

    path = tmp_path / "hostile.mcap"
    _hostile_ros2_log(path, sample_images(6, size=(160, 120)))
    reader = McapLogReader(path)
    assert len(list(reader.frames())) == 5 and len(reader.results) == 5
    assert reader.status.undecodable_messages == 1 and reader.status.invalid_messages == 2

    bundle = make_synthetic_bundle(tmp_path / "bundle")
    with caplog.at_level(logging.INFO, logger="aefabmap.replay"):
        assert cli_replay.main(cli_args("replay", path, "--model", bundle)) == 0
    lines = [r.getMessage() for r in caplog.records if "failed validation" in r.getMessage()]
    assert len(lines) == 1 and "\n" not in lines[0] and "read 12 messages (5 images" in lines[0]
    assert "2 messages failed validation" in lines[0]


@pytest.mark.slow
@pytest.mark.timeout(240)
def test_cli_run_with_the_ros2_profile_then_replay_check(tmp_path):
    """`aefabmap run --mcap-profile ros2` as a process with a real bundle; rosbags reads its log;
    `aefabmap replay --check --out --mcap-profile ros2` passes and writes a ros2 log too."""
    import subprocess

    from aefabmap_runtime.tools.synthetic_route import make_demo_sequence

    bundle = make_synthetic_bundle(tmp_path / "bundle")
    make_demo_sequence(tmp_path / "seq", n_frames=16, seed=2, size=(160, 120))
    log_path = tmp_path / "run.mcap"
    node = run_node_process(["--model", str(bundle), "--mcap", str(log_path), "--queue", "32",
                             "--mcap-profile", "ros2"], tmp_path / "seq", 15, rate=50, timeout_s=60)
    assert node.returncode == 0, node.stderr
    types, messages = rosbags_messages(log_path)
    assert types == TYPES and len(messages[ROS2_IMAGE_TOPIC]) == 16 and len(messages["/lcd/result"]) == 16
    out = tmp_path / "re.mcap"
    rep = subprocess.run(CLI + ["replay", str(log_path), "--model", str(bundle), "--check", "--out", str(out),
                                "--mcap-profile", "ros2"], capture_output=True, text=True, timeout=120)
    assert rep.returncode == 0, rep.stderr
    assert json.loads(rep.stdout.strip().splitlines()[-1])["check"]["compared"] == 16
    types, messages = rosbags_messages(out)
    assert types == TYPES and len(messages["/lcd/result"]) == 16
