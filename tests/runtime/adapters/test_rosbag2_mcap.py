"""ros2-profile logs as rosbag2 writes MCAP (runtime/aefabmap_runtime/adapters/rosbag2_mcap.py).

Read the way the ROS side reads them, with other code than ours: each channel's
``offered_qos_profiles`` parsed as the YAML QoS list of rosbag2's metadata version 8 (ruamel, as
rosbags parses it, and rosbags' own parse_qos); the ``rosbag2`` metadata record parsed and used as
the ``metadata.yaml`` of a rosbag2 directory by rosbags' bag reader (which matches its topics,
types and QoS against the file's channels); /diagnostics decoded by rosbags and mcap-ros2-support.
A ROS 2 run through a real router logs the DiagnosticArray samples a ROS subscriber received.
"""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

import pytest
import zenoh
from mcap.reader import make_reader

from aefabmap_runtime.adapters.log_repair import repair_log
from aefabmap_runtime.adapters.mcap_log import McapLogConfig, McapLogWriter
from aefabmap_runtime.adapters.rmw_zenoh import DIAGNOSTIC_ARRAY_RIHS01, IMAGE_RIHS01, RosOptions
from aefabmap_runtime.adapters.zenoh_transport import build_zenoh_config

from .stream_fakes import FakeDetector, NodeThread, record_live_log, sample_images
from .test_mcap_ros2_profile import ROS2, STAMP0, TYPES, _write_frames, mcap_ros2_decoded, rosbags_messages
from .test_rmw_zenoh import TOPIC, Router, rmw_attachment, ros_image
from .test_rmw_zenoh_diagnostics import Collector, wait_matching

rosbags_typesys = pytest.importorskip("rosbags.typesys")
pytestmark = pytest.mark.timeout(120)

#: The keys of one QoS profile as rosbag2 serialises it (rosbag2_storage qos.cpp).
QOS_KEYS = {"history", "depth", "reliability", "durability", "deadline", "lifespan", "liveliness",
            "liveliness_lease_duration", "avoid_ros_namespace_conventions"}


def yaml_load(text: str):
    from ruamel.yaml import YAML  # rosbags' YAML parser

    return YAML(typ="safe").load(text)


def channels(path: Path) -> dict[str, dict[str, str]]:
    """{topic: channel metadata} of an MCAP file."""
    with open(path, "rb") as f:
        return {c.topic: dict(c.metadata) for c in make_reader(f).get_summary().channels.values()}


def rosbag2_records(path: Path) -> list[dict]:
    """The parsed ``serialized_metadata`` of every ``rosbag2`` metadata record of a file."""
    with open(path, "rb") as f:
        records = [m for m in make_reader(f).iter_metadata() if m.name == "rosbag2"]
    assert all(set(m.metadata) == {"serialized_metadata"} for m in records)
    return [yaml_load(m.metadata["serialized_metadata"]) for m in records]


def log_times(path: Path) -> list[int]:
    with open(path, "rb") as f:
        return [m.log_time for _, _, m in make_reader(f).iter_messages(log_time_order=False)]


def check_record(path: Path, doc: dict, *, name: str | None = None) -> None:
    """doc is the rosbag2 metadata of file ``path``: topics, types, counts, times and QoS as the
    file holds them; rosbags' bag reader opens ``path`` with doc as its metadata.yaml."""
    from rosbags.rosbag2 import Reader

    _, messages = rosbags_messages(path)
    meta = channels(path)
    assert doc["version"] == 8 and doc["storage_identifier"] == "mcap"
    assert doc["relative_file_paths"] == [name or path.name]
    topics = {t["topic_metadata"]["name"]: t for t in doc["topics_with_message_count"]}
    assert set(topics) == set(meta)
    for topic, entry in topics.items():
        tm = entry["topic_metadata"]
        assert tm["serialization_format"] == "cdr" and entry["message_count"] == len(messages.get(topic, []))
        assert tm["offered_qos_profiles"] == meta[topic]["offered_qos_profiles"]
        assert tm["type_description_hash"] == meta[topic]["topic_type_hash"]
    times = log_times(path)
    assert doc["message_count"] == len(times) == sum(len(v) for v in messages.values())
    assert doc["starting_time"]["nanoseconds_since_epoch"] == min(times)
    assert doc["duration"]["nanoseconds"] == max(times) - min(times)
    assert doc["files"] == [{"path": doc["relative_file_paths"][0], "starting_time": doc["starting_time"],
                             "duration": doc["duration"], "message_count": doc["message_count"]}]
    assert doc["custom_data"] == {} and doc["ros_distro"] == ""

    bag = path.parent / f"{path.stem}-bag"  # the record as a rosbag2 directory's metadata.yaml
    bag.mkdir()
    (bag / doc["relative_file_paths"][0]).symlink_to(path.resolve())
    (bag / "metadata.yaml").write_text(json.dumps({"rosbag2_bagfile_information": doc}))
    with Reader(bag) as reader:
        assert {c.topic: (c.msgtype, c.msgcount) for c in reader.connections} == {
            t: (TYPES[t], topics[t]["message_count"]) for t in topics}
        assert reader.message_count == doc["message_count"]
        assert Counter(c.topic for c, _, _ in reader.messages()) == Counter(
            {t: len(v) for t, v in messages.items()})


@pytest.fixture(scope="module")
def live_run(tmp_path_factory):
    """A live node's ros2-profile log (16 frames, stats every 0.2 s)."""
    path = tmp_path_factory.mktemp("rosbag2") / "run.mcap"
    summary, _ = record_live_log(path, stats_period_s=0.2, log_config=ROS2)
    assert summary.frames_processed == 16
    return path


def test_every_channel_offers_the_publishers_qos_as_rosbag2_writes_it(live_run):
    from rosbags.highlevel import AnyReader
    from rosbags.interfaces import QosDurability, QosHistory, QosReliability
    from rosbags.rosbag2.metadata import parse_qos

    ts = rosbags_typesys.get_typestore(rosbags_typesys.Stores.ROS2_JAZZY)
    meta = channels(live_run)
    assert set(meta) == set(TYPES)
    for topic, md in meta.items():
        profiles = yaml_load(md["offered_qos_profiles"])
        assert isinstance(profiles, list) and len(profiles) == 1 and set(profiles[0]) == QOS_KEYS, topic
        qos = profiles[0]
        assert all(isinstance(qos[k], int) for k in ("history", "reliability", "durability", "liveliness"))
        assert all(set(qos[k]) == {"sec", "nsec"} for k in ("deadline", "lifespan", "liveliness_lease_duration"))
        (parsed,) = parse_qos(md["offered_qos_profiles"])
        assert (parsed.history, parsed.depth, parsed.reliability, parsed.durability) == (
            QosHistory.KEEP_LAST, 10, QosReliability.RELIABLE, QosDurability.VOLATILE)
        assert md["topic_type_hash"] == ts.hash_rihs01(TYPES[topic])
    with AnyReader([live_run], default_typestore=ts) as reader:
        assert {c.topic: c.ext.offered_qos_profiles for c in reader.connections} == {
            t: parse_qos(md["offered_qos_profiles"]) for t, md in meta.items()}


def test_the_rosbag2_record_lists_every_topic_with_its_count_and_opens_as_a_bag(live_run):
    (doc,) = rosbag2_records(live_run)
    check_record(live_run, doc)
    counts = {t["topic_metadata"]["name"]: t["message_count"] for t in doc["topics_with_message_count"]}
    assert counts["/camera/image/compressed"] == counts["/lcd/result"] == 16
    assert counts["/diagnostics"] == counts["/lcd/stats"] >= 2


def test_diagnostics_are_logged_with_every_stats_message_and_decode(live_run):
    _, messages = rosbags_messages(live_run)
    stats = [json.loads(m.data) for m in messages["/lcd/stats"]]
    diags = messages["/diagnostics"]
    assert len(diags) == len(stats) >= 2
    for diag, doc in zip(diags, stats):
        (status,) = diag.status
        values = {kv.key: kv.value for kv in status.values}
        assert diag.header.stamp.sec * 10**9 + diag.header.stamp.nanosec == doc["stamp_ns"]
        assert status.name == "aefabmap" and status.hardware_id and status.level == 0
        assert values["frames_processed"] == str(doc["frames_processed"]) and values["log_state"] == "ok"
    assert values["frames_processed"] == "16"
    assert mcap_ros2_decoded(live_run) == sum(len(v) for v in messages.values())


def test_a_ros2_run_logs_the_diagnostics_it_published(tmp_path):
    """A node on rmw_zenoh (a real router on loopback) with a ros2-profile log: the
    DiagnosticArray samples a ROS subscriber received are the ones logged on /diagnostics, with
    the node's status (places, map size) that diagnostics made from stats alone lack."""
    ts = rosbags_typesys.get_typestore(rosbags_typesys.Stores.ROS2_JAZZY)
    log = tmp_path / "ros.mcap"
    router = Router()
    try:
        with (
            NodeThread(detector=FakeDetector(), session_config=router.ros_peer(), key="unused", mcap_path=log,
                       queue_size=16, stats_period_s=0.2, log_config=ROS2, ros=RosOptions(topic=TOPIC)) as node,
            zenoh.open(build_zenoh_config(router.ros_peer())) as camera,
        ):
            diags = Collector(camera, f"0/diagnostics/diagnostic_msgs::msg::dds_::DiagnosticArray_/"
                                      f"{DIAGNOSTIC_ARRAY_RIHS01}")
            pub = camera.declare_publisher(f"0/camera/image_raw/sensor_msgs::msg::dds_::Image_/{IMAGE_RIHS01}",
                                           congestion_control=zenoh.CongestionControl.BLOCK)
            wait_matching(pub)
            for i, img in enumerate(sample_images(4, size=(160, 120))):
                pub.put(ros_image(ts, img, "mono8", STAMP0 + i), attachment=rmw_attachment(i + 1, STAMP0 + i))

            def processed(items) -> bool:
                return any({kv.key: kv.value for kv in ts.deserialize_cdr(p, "diagnostic_msgs/msg/DiagnosticArray")
                            .status[0].values}.get("frames_processed") == "4" for p, _ in items)

            received = [p for p, _ in diags.wait(processed)]
            node.finish()
    finally:
        router.close()
    _, messages = rosbags_messages(log)
    with open(log, "rb") as f:
        logged = [m.data for _, c, m in make_reader(f).iter_messages() if c.topic == "/diagnostics"]
    # One DiagnosticArray per stats message; those before the camera's first sample (its distribution
    # not yet known: nothing published) made from the stats, then the published ones, as they went out.
    names = [ts.deserialize_cdr(d, "diagnostic_msgs/msg/DiagnosticArray").status[0].name for d in logged]
    assert len(logged) == len(messages["/lcd/stats"])
    published = [d for d, name in zip(logged, names) if name == "aefabmap: aefabmap"]
    assert names == ["aefabmap"] * (len(logged) - len(published)) + ["aefabmap: aefabmap"] * len(published)
    assert published[:len(received)] == received
    values = {kv.key: kv.value for kv in messages["/diagnostics"][-1].status[0].values}
    assert values["places"] and "map_mb" in values and values["ros_distro"] == "jazzy"
    assert messages["/diagnostics"][-1].status[0].name == "aefabmap: aefabmap"
    (doc,) = rosbag2_records(log)
    check_record(log, doc)


def test_rotated_files_each_carry_their_own_record(tmp_path):
    from aefabmap_runtime.adapters.log_set import log_files
    from aefabmap_runtime.adapters.rotating_log import LogRotationConfig, RotatingLog

    rotation = LogRotationConfig(max_mb=0.05, summary_reserve_bytes=4096, images_min_free_mb=0.0,
                                 results_min_free_mb=0.0)
    (tmp_path / "set").mkdir()
    with RotatingLog(tmp_path / "set", ROS2, rotation, manifest=FakeDetector().manifest) as log:
        log.open()
        _write_frames(log, sample_images(30, size=(96, 72)), FakeDetector())
        log.write_stats({"stamp_ns": STAMP0, "frames_processed": 30})
    files = log_files(tmp_path / "set")
    assert len(files) >= 3
    for f in files:
        (doc,) = rosbag2_records(f)
        check_record(f, doc)
    assert sum(len(rosbags_messages(f)[1].get("/diagnostics", [])) for f in files) == 1


def test_a_cut_ros2_log_gets_a_record_of_what_the_repair_kept(tmp_path):
    whole = tmp_path / "whole.mcap"
    with McapLogWriter(whole, McapLogConfig(profile="ros2", chunk_size=4096)) as w:
        _write_frames(w, sample_images(30, size=(96, 72)), FakeDetector())
        w.write_stats({"stamp_ns": STAMP0, "frames_processed": 30})
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(whole.read_bytes()[: int(whole.stat().st_size * 0.7)])
    report = repair_log(cut, tmp_path / "fixed.mcap")
    assert report.truncated and 0 < report.messages < 62
    (doc,) = rosbag2_records(tmp_path / "fixed.mcap")
    check_record(tmp_path / "fixed.mcap", doc)
    assert doc["message_count"] == report.messages
    repair_log(whole, tmp_path / "again.mcap")  # a finished file: its own record, not a second one
    (again,) = rosbag2_records(tmp_path / "again.mcap")
    assert again == rosbag2_records(whole)[0] and again["message_count"] == 62


def test_topic_names_reach_the_record_exactly_whatever_they_hold(tmp_path):
    """The record's YAML quotes every string: a topic with YAML syntax in its name stays a name."""
    odd = '/cam: "x" #y\n- z'
    path = tmp_path / "odd.mcap"
    with McapLogWriter(path, McapLogConfig(profile="ros2", image_topic=odd)) as w:
        _write_frames(w, sample_images(2, size=(96, 72)), FakeDetector())
    (doc,) = rosbag2_records(path)
    names = [t["topic_metadata"]["name"] for t in doc["topics_with_message_count"]]
    assert names == [odd, "/lcd/result", "/lcd/stats", "/diagnostics"]
    assert [t["message_count"] for t in doc["topics_with_message_count"]] == [2, 2, 0, 0]
