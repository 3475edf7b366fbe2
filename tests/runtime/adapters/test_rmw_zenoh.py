"""ROS 2 over rmw_zenoh without a bridge (runtime/aefabmap_runtime/adapters/rmw_zenoh.py, ros_cdr.py).

The samples are made the way a ROS 2 node using rmw_zenoh makes them, but with other
tools than the runtime's own: CDR by rosbags' serializer, the attachment by zenoh-ext's
serializer (``z_serialize``), the key with Humble's ``TypeHashNotSupported``; they travel
through a real Zenoh router on loopback, like rmw_zenoh's ``rmw_zenohd``.
"""

from __future__ import annotations

import json
import threading
import time

import cv2
import numpy as np
import pytest
import zenoh
from zenoh.ext import Int64, z_serialize

from aefabmap_runtime.errors import ConfigError
from aefabmap_runtime.adapters.frames import FrameError, decode_frame
from aefabmap_runtime.adapters.rmw_zenoh import (
    COMPRESSED_IMAGE_RIHS01,
    IMAGE_RIHS01,
    STRING_RIHS01,
    RosOptions,
    liveliness_token,
    meta_from_attachment,
    parse_attachment,
)
from aefabmap_runtime.adapters.ros_cdr import decode_compressed_cdr, decode_image_cdr
from aefabmap_runtime.adapters.zenoh_transport import SessionConfig, build_zenoh_config

from .stream_fakes import FakeDetector, NodeThread, free_tcp_port, sample_images
from tests.conftest import cli_args

rosbags_typesys = pytest.importorskip("rosbags.typesys")
pytestmark = pytest.mark.timeout(90)

TOPIC = "/camera/image_raw"
IMAGE_KEY = "0/camera/image_raw/sensor_msgs::msg::dds_::Image_/TypeHashNotSupported"
COMPRESSED_KEY = "0/camera/image_raw/sensor_msgs::msg::dds_::CompressedImage_/TypeHashNotSupported"
RESULT_KEY = "0/lcd/result/std_msgs::msg::dds_::String_/TypeHashNotSupported"
GID = bytes(range(100, 116))
STAMP0 = 1_700_000_000_000_000_000


@pytest.fixture(scope="module")
def typestore():
    return rosbags_typesys.get_typestore(rosbags_typesys.Stores.ROS2_HUMBLE)


def ros_image(ts, gray: np.ndarray, encoding: str, stamp_ns: int) -> bytes:
    """A sensor_msgs/msg/Image in CDR, serialised by rosbags (not by the runtime)."""
    T = ts.types
    img = gray if encoding == "mono8" else cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR)
    h, w = gray.shape
    step = w * (1 if encoding == "mono8" else 3)
    header = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9,
                                                                              nanosec=stamp_ns % 10**9),
                                      frame_id="camera")
    msg = T["sensor_msgs/msg/Image"](header=header, height=h, width=w, encoding=encoding, is_bigendian=0,
                                     step=step, data=np.ascontiguousarray(img).reshape(-1))
    return bytes(ts.serialize_cdr(msg, "sensor_msgs/msg/Image"))


def ros_compressed(ts, gray: np.ndarray, stamp_ns: int) -> bytes:
    T = ts.types
    ok, jpeg = cv2.imencode(".jpg", gray)
    assert ok
    header = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9,
                                                                              nanosec=stamp_ns % 10**9),
                                      frame_id="camera")
    msg = T["sensor_msgs/msg/CompressedImage"](header=header, format="jpeg", data=jpeg.reshape(-1))
    return bytes(ts.serialize_cdr(msg, "sensor_msgs/msg/CompressedImage"))


def rmw_attachment(seq: int, stamp_ns: int) -> bytes:
    """rmw_zenoh's attachment as zenoh-ext serialises it (int64, int64, 16-byte gid)."""
    return z_serialize((Int64(seq), Int64(stamp_ns), GID)).to_bytes()


class Router:
    """A Zenoh router on a loopback port, standing in for rmw_zenohd."""

    def __init__(self) -> None:
        self.endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
        self.session = zenoh.open(build_zenoh_config(SessionConfig(listen=(self.endpoint,), mode="router")))

    def ros_peer(self) -> SessionConfig:
        """A ROS 2 node's session as rmw_zenoh opens it (and ``aefabmap run --ros-topic``): a peer
        that connects to the router and listens on a loopback port."""
        return SessionConfig(connect=(self.endpoint,), listen=("tcp/127.0.0.1:0",), mode="peer")

    def close(self) -> None:
        self.session.close()


class RosResults:
    """Collects /lcd/result std_msgs/String messages, decoded by rosbags."""

    def __init__(self, session, ts, key: str = RESULT_KEY) -> None:
        self.docs: list[dict] = []
        self.attachments: list[bytes] = []
        self.cond = threading.Condition()

        def on_sample(sample) -> None:
            msg = ts.deserialize_cdr(sample.payload.to_bytes(), "std_msgs/msg/String")
            with self.cond:
                self.docs.append(json.loads(msg.data))
                self.attachments.append(sample.attachment.to_bytes())
                self.cond.notify_all()

        self.sub = session.declare_subscriber(key, on_sample)

    def wait_for(self, n: int, timeout_s: float) -> list[dict]:
        with self.cond:
            assert self.cond.wait_for(lambda: len(self.docs) >= n, timeout_s), f"got {len(self.docs)} of {n} results"
            return list(self.docs)


def graph_tokens(session, domain: int = 0, timeout_s: float = 10.0) -> list[str]:
    """The ROS 2 graph's liveliness tokens as ``session`` lists them (liveliness get), once the
    node's own are all there (its node token, three publishers, its subscription) or timeout_s
    passed: with peers, a token can reach a newly connected peer a moment after the data does."""
    deadline = time.monotonic() + timeout_s
    pause = threading.Event()
    while True:
        tokens = [str(r.ok.key_expr) for r in session.liveliness().get(f"@ros2_lv/{domain}/**") if r.ok is not None]
        kinds = [t.split("/")[5] for t in tokens if len(t.split("/")) > 5]
        if (kinds.count("NN") >= 1 and kinds.count("MP") >= 3 and kinds.count("MS") >= 1) \
                or time.monotonic() > deadline:
            return tokens
        pause.wait(0.1)


def _publish_and_collect(tmp_path, typestore, frames, expect: int, distro: str = "humble",
                         result_key: str = RESULT_KEY, **ros):
    """frames: (key, payload, seq) tuples; returns (summary, results, graph tokens, ros results);
    graph tokens as listed once every result arrived."""
    router = Router()
    try:
        with (
            NodeThread(detector=FakeDetector(), session_config=router.ros_peer(), key="unused",
                       mcap_path=tmp_path / "ros.mcap", queue_size=16, stats_period_s=0.2,
                       ros=RosOptions(topic=TOPIC, distro=distro, **ros)) as node,
            zenoh.open(build_zenoh_config(router.ros_peer())) as camera,
        ):
            results = RosResults(camera, typestore, result_key)
            pubs = {key: camera.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
                    for key in {k for k, _, _ in frames}}
            pause = threading.Event()
            for pub in pubs.values():  # wait (bounded) until the node's subscription is routed to us
                for _ in range(200):
                    if pub.matching_status.matching:
                        break
                    pause.wait(0.05)
                assert pub.matching_status.matching
            for key, payload, seq in frames:
                pubs[key].put(payload, attachment=rmw_attachment(seq, STAMP0 + seq))
            docs = results.wait_for(expect, timeout_s=20)
            tokens = graph_tokens(camera)
            summary = node.finish()
            results.sub.undeclare()
            return summary, docs, tokens, results.attachments
    finally:
        router.close()


def test_rmw_zenoh_image_samples_give_one_result_each(tmp_path, typestore):
    images = sample_images(3, size=(160, 120))
    stamps = [STAMP0 + 10**9 * (i + 1) + 123 for i in range(3)]
    frames = [
        (IMAGE_KEY, ros_image(typestore, images[0], "mono8", stamps[0]), 1),
        (IMAGE_KEY, ros_image(typestore, images[1], "bgr8", stamps[1]), 2),
        (COMPRESSED_KEY, ros_compressed(typestore, images[2], stamps[2]), 3),
    ]
    summary, docs, tokens, atts = _publish_and_collect(tmp_path, typestore, frames, expect=3)
    assert summary.frames_processed == 3 and summary.dropped == 0 and summary.bad_total == 0
    assert [d["sequence"] for d in docs] == [0, 1, 2]
    assert [d["stamp_ns"] for d in docs] == stamps  # the header stamps, not receive times
    assert [d["frame_seq"] for d in docs] == [1, 2, 3]
    # Our results carry rmw_zenoh's attachment (numbered from 1) and the node is in the graph.
    assert [parse_attachment(a).sequence_number for a in atts] == [1, 2, 3]
    assert all(len(parse_attachment(a).gid) == 16 for a in atts)  # rmw_zenoh's Humble port hard-codes 16
    assert any("/NN/%/%/aefabmap" in t for t in tokens)
    assert any(t.endswith("/MP/%/%/aefabmap/%lcd%result/std_msgs::msg::dds_::String_/TypeHashNotSupported/::,:,:,:,,")
               for t in tokens)
    assert any("/MS/%/%/aefabmap/%camera%image_raw/sensor_msgs::msg::dds_::Image_/" in t for t in tokens)


def test_a_jazzy_camera_with_default_options_gets_its_results_under_rihs01(tmp_path, typestore):
    """The distribution comes from the wire: a camera publishing under RIHS01 hashes (Jazzy and
    later) gets results on the String topic with the RIHS01 hash and 16-byte gids, and the graph
    lists the node's topics with that hash."""
    images = sample_images(3, size=(160, 120))
    key = f"0/camera/image_raw/sensor_msgs::msg::dds_::Image_/{IMAGE_RIHS01}"
    frames = [(key, ros_image(typestore, img, "mono8", STAMP0 + i), i + 1) for i, img in enumerate(images)]
    result_key = f"0/lcd/result/std_msgs::msg::dds_::String_/{STRING_RIHS01}"
    summary, docs, tokens, atts = _publish_and_collect(tmp_path, typestore, frames, expect=3, distro="auto",
                                                       result_key=result_key)
    assert summary.frames_processed == 3 and [d["sequence"] for d in docs] == [0, 1, 2]
    assert all(len(parse_attachment(a).gid) == 16 for a in atts)
    assert any(t.endswith(f"/MP/%/%/aefabmap/%lcd%result/std_msgs::msg::dds_::String_/{STRING_RIHS01}/"
                          "::,:,:,:,,") for t in tokens)
    assert any(f"/MS/%/%/aefabmap/%camera%image_raw/sensor_msgs::msg::dds_::Image_/{IMAGE_RIHS01}" in t
               for t in tokens)
    assert not any("TypeHashNotSupported" in t for t in tokens if "/aefabmap/" in t)


def test_a_compressed_image_camera_sees_one_type_on_its_topic(tmp_path, typestore):
    """The subscription token claims the camera's own type and hash (CompressedImage here), so
    `ros2 topic list -t` shows one type on the camera topic."""
    images = sample_images(2, size=(160, 120))
    key = f"0/camera/image_raw/sensor_msgs::msg::dds_::CompressedImage_/{COMPRESSED_IMAGE_RIHS01}"
    frames = [(key, ros_compressed(typestore, img, STAMP0 + i), i + 1) for i, img in enumerate(images)]
    result_key = f"0/lcd/result/std_msgs::msg::dds_::String_/{STRING_RIHS01}"
    _, _, tokens, _ = _publish_and_collect(tmp_path, typestore, frames, expect=2, distro="auto",
                                           result_key=result_key)
    ours = [t for t in tokens if "/MS/" in t and "/aefabmap/" in t]
    assert len(ours) == 1 and f"sensor_msgs::msg::dds_::CompressedImage_/{COMPRESSED_IMAGE_RIHS01}" in ours[0]


#: rmw's QoS policy values (rmw/types.h) and rmw_zenoh's defaults (qos.cpp), which a token leaves out.
RMW_RELIABLE, RMW_BEST_EFFORT, RMW_VOLATILE, RMW_KEEP_LAST = 1, 2, 2, 1
RMW_ZENOH_DEFAULTS = {"reliability": RMW_RELIABLE, "durability": RMW_VOLATILE, "history": RMW_KEEP_LAST, "depth": 42}


def token_qos(token: str) -> dict[str, int]:
    """A liveliness token's QoS as rmw_zenoh reads it (liveliness_utils.cpp, keyexpr_to_qos): the
    last chunk is ``<reliability>:<durability>:<history>,<depth>:<deadline>:<lifespan>:<liveliness>``
    (the last three comma-separated), an empty field meaning rmw_zenoh's default."""
    parts = token.rsplit("/", 1)[1].split(":")
    assert len(parts) == 6 and [p.count(",") for p in parts[2:]] == [1, 1, 1, 2], token
    history, depth = parts[2].split(",")
    given = {"reliability": parts[0], "durability": parts[1], "history": history, "depth": depth}
    return {k: int(v) if v else RMW_ZENOH_DEFAULTS[k] for k, v in given.items()}


def test_the_image_subscription_advertises_the_sensor_data_qos_cameras_publish(tmp_path, typestore):
    """Cameras publish with the sensor-data profile: the node's subscription token says best
    effort, volatile, keep last (its frame queue, 16 here); its publishers keep rmw_zenoh's default."""
    images = sample_images(2, size=(160, 120))
    key = f"0/camera/image_raw/sensor_msgs::msg::dds_::Image_/{IMAGE_RIHS01}"
    frames = [(key, ros_image(typestore, img, "mono8", STAMP0 + i), i + 1) for i, img in enumerate(images)]
    result_key = f"0/lcd/result/std_msgs::msg::dds_::String_/{STRING_RIHS01}"
    _, _, tokens, _ = _publish_and_collect(tmp_path, typestore, frames, expect=2, distro="auto",
                                           result_key=result_key)
    (sub,) = [t for t in tokens if "/MS/" in t and "/aefabmap/" in t]
    assert token_qos(sub) == {"reliability": RMW_BEST_EFFORT, "durability": RMW_VOLATILE, "history": RMW_KEEP_LAST,
                              "depth": 16}
    pubs = [t for t in tokens if "/MP/" in t and "/aefabmap/" in t]
    assert len(pubs) == 3 and all(token_qos(t) == RMW_ZENOH_DEFAULTS for t in pubs)


def test_namespace_node_name_and_topics_are_the_users(tmp_path, typestore):
    images = sample_images(2, size=(160, 120))
    frames = [(IMAGE_KEY, ros_image(typestore, img, "mono8", STAMP0 + i), i + 1) for i, img in enumerate(images)]
    key = "0/robot1/loops/std_msgs::msg::dds_::String_/TypeHashNotSupported"
    _, docs, tokens, _ = _publish_and_collect(tmp_path, typestore, frames, expect=2, result_key=key,
                                              namespace="/robot1", node="lcd", result_topic="loops")
    assert [d["sequence"] for d in docs] == [0, 1]
    assert any("/NN/%/%robot1/lcd" in t for t in tokens)
    assert any("/MP/%/%robot1/lcd/%robot1%loops/std_msgs::msg::dds_::String_/" in t for t in tokens)
    assert any("/MP/%/%robot1/lcd/%robot1%lcd%stats/" in t for t in tokens)
    for bad in ({"namespace": "robot 1"}, {"node": "a/b"}, {"result_topic": "bad topic"}):
        with pytest.raises(ConfigError):
            RosOptions(topic=TOPIC, **bad)


def test_ros_domain_id_from_the_environment_and_refused_when_malformed():
    from aefabmap_runtime.errors import ConfigError
    from aefabmap_runtime.adapters.rmw_zenoh import domain_from_env

    assert domain_from_env({}) == 0 and domain_from_env({"ROS_DOMAIN_ID": " 3 "}) == 3
    for bad in ("x", "-1", "233", "3.5"):
        with pytest.raises(ConfigError):
            domain_from_env({"ROS_DOMAIN_ID": bad})


def test_rmw_zenoh_dropped_sequence_number_and_hostile_samples_are_counted(tmp_path, typestore):
    images = sample_images(3, size=(160, 120))
    good = [ros_image(typestore, img, "mono8", STAMP0 + i + 1) for i, img in enumerate(images)]
    text = bytes(typestore.serialize_cdr(typestore.types["std_msgs/msg/String"](data="hi"), "std_msgs/msg/String"))
    frames = [
        (IMAGE_KEY, good[0], 1),
        (IMAGE_KEY, good[1][: len(good[1]) // 2], 2),  # truncated CDR: corrupt
        ("0/camera/image_raw/std_msgs::msg::dds_::String_/TypeHashNotSupported", text, 3),  # wrong type
        (IMAGE_KEY, good[1], 4),
        (IMAGE_KEY, good[2], 6),  # sequence number 5 never arrives: one drop
    ]
    summary, docs, _, _ = _publish_and_collect(tmp_path, typestore, frames, expect=3)
    assert summary.frames_processed == 3 and summary.dropped == 1
    assert {k: v for k, v in summary.bad.items() if v} == {"corrupt": 1, "wrong_encoding": 1}
    assert [d["frame_seq"] for d in docs] == [1, 4, 6]


def test_cli_run_takes_a_key_or_a_ros_topic(tmp_path):
    from aefabmap.cli.main import main

    base = ["run", "--model", str(tmp_path / "none"), "--mcap", str(tmp_path / "x.mcap")]
    assert main([*base, "--key", "robot/camera/image", "--ros-topic", "/camera/image_raw"]) == 2
    assert main(base) == 2
    assert main([*base, "--ros-topic", "/camera/image raw"]) == 2  # not a ROS name


def test_cdr_reader_matches_rosbags_and_refuses_every_truncation(typestore):
    gray = sample_images(1, size=(40, 32))[0]
    for enc in ("mono8", "bgr8"):
        data = ros_image(typestore, gray, enc, STAMP0 + 5)
        img = decode_image_cdr(data)
        assert img.stamp_ns == STAMP0 + 5 and img.frame_id == "camera"
        assert np.array_equal(decode_frame(img.payload, img.encoding), gray) or enc == "bgr8"
        for cut in range(len(data) - 1):
            with pytest.raises(FrameError):
                decode_image_cdr(data[:cut])
    comp = ros_compressed(typestore, gray, STAMP0)
    assert decode_compressed_cdr(comp).encoding == "image/jpeg"
    for cut in range(0, len(comp) - 1, 7):
        with pytest.raises(FrameError):
            decode_frame(*_compressed_frame(comp[:cut]))
    # A length field claiming more than the buffer holds is refused, not sliced.
    evil = bytearray(ros_image(typestore, gray, "mono8", STAMP0))
    evil[-len(gray.tobytes()) - 4: -len(gray.tobytes())] = (2**32 - 1).to_bytes(4, "little")
    with pytest.raises(FrameError) as info:
        decode_image_cdr(bytes(evil))
    assert info.value.reason == "corrupt"


def _compressed_frame(data: bytes) -> tuple[bytes, str]:
    img = decode_compressed_cdr(data)
    return img.payload, img.encoding


def test_attachment_layouts_and_hostile_attachments():
    current = rmw_attachment(7, 99)
    assert parse_attachment(current).sequence_number == 7 and parse_attachment(current).gid == GID
    keyed = z_serialize(("sequence_number", Int64(7), "source_timestamp", Int64(99), "source_gid", GID)).to_bytes()
    assert parse_attachment(keyed) == parse_attachment(current)
    humble_gid = GID + bytes(8)  # RMW_GID_STORAGE_SIZE is 24 on Humble
    humble = z_serialize((Int64(7), Int64(99), humble_gid)).to_bytes()
    assert parse_attachment(humble).gid == humble_gid
    with_zid = z_serialize((Int64(7), Int64(99), GID, "3f2a")).to_bytes()
    assert parse_attachment(with_zid) == parse_attachment(current)
    meta = meta_from_attachment(current)
    assert (meta.seq, meta.stamp_ns, meta.src, meta.problem) == (7, 99, GID.hex(), "")
    for bad in (b"", current[:-1], current + b"\x00\x00", b'{"seq": 1}', current[:16] + b"\x11" + GID + b"x",
                current[:16] + b"\x08" + GID[:8], current + b"\x05ab"):
        assert meta_from_attachment(bad).problem


def test_graph_names_and_string_type_hash(typestore):
    jazzy = rosbags_typesys.get_typestore(rosbags_typesys.Stores.ROS2_JAZZY)
    assert jazzy.hash_rihs01("std_msgs/msg/String") == STRING_RIHS01
    assert jazzy.hash_rihs01("sensor_msgs/msg/Image") == IMAGE_RIHS01
    assert jazzy.hash_rihs01("sensor_msgs/msg/CompressedImage") == COMPRESSED_IMAGE_RIHS01
    token = liveliness_token(0, "abc", 0, 2, "MP", "aefabmap", "/lcd/result", "std_msgs/msg/String",
                             "TypeHashNotSupported")
    assert token == ("@ros2_lv/0/abc/0/2/MP/%/%/aefabmap/%lcd%result/std_msgs::msg::dds_::String_/"
                     "TypeHashNotSupported/::,:,:,:,,")
    assert RosOptions(topic="/camera/image_raw").image_key == "0/camera/image_raw/*/*"
    assert RosOptions(topic="/camera/image_raw").default_results_key == "camera/lcd"


def run_cli_while(drive, args, router, capsys) -> dict:
    """Run `aefabmap run` (args) in this process while `drive()` talks to it through `router` on a
    thread; when drive ends, SIGINT stops the node. Checks drive raised nothing and the node exited
    0, closes the router, and returns the node's last JSON line (its summary)."""
    import os
    import signal

    from aefabmap.cli import run

    errors: list[BaseException] = []
    done = threading.Event()

    def driver() -> None:
        try:
            drive()
            done.set()
        except BaseException as exc:  # noqa: BLE001 - reported to the test
            errors.append(exc)
        finally:
            os.kill(os.getpid(), signal.SIGINT)

    thread = threading.Thread(target=driver, daemon=True)
    thread.start()
    try:
        code = run.main(args)
        thread.join(10)
    finally:
        router.close()
    assert not errors and done.is_set()
    assert code == 0
    return json.loads(capsys.readouterr().out.strip().splitlines()[-1])


def test_cli_run_ros_topic_through_a_router(tmp_path, typestore, monkeypatch, capsys):
    """`aefabmap run --ros-topic ... --connect <router> --results-key robot/lcd` end to end."""
    import aefabmap_runtime.adapters.bundle_reader as bundle_reader_mod
    from aefabmap_runtime.adapters.mcap_log import RUN_CONFIG_METADATA, McapLogReader

    from .stream_fakes import JsonCollector

    monkeypatch.setattr(bundle_reader_mod, "load_detector", lambda *a, **k: FakeDetector())
    router = Router()
    log_path = tmp_path / "cli_ros.mcap"
    args = cli_args("run", "--model", "fake", "--ros-topic", TOPIC, "--results-key", "robot/lcd",
                    "--connect", router.endpoint, "--mcap", log_path, "--queue", "4")

    def drive() -> None:
        with zenoh.open(build_zenoh_config(router.ros_peer())) as camera:
            plain = JsonCollector(camera, "robot/lcd")
            ros = RosResults(camera, typestore)
            pub = camera.declare_publisher(IMAGE_KEY, congestion_control=zenoh.CongestionControl.BLOCK)
            pause = threading.Event()
            for _ in range(400):
                if pub.matching_status.matching:
                    break
                pause.wait(0.05)
            for i, img in enumerate(sample_images(2, size=(96, 72))):
                pub.put(ros_image(typestore, img, "mono8", STAMP0 + i), attachment=rmw_attachment(i + 1, STAMP0))
            plain.wait_for(lambda d: d["sequence"] == 1, timeout_s=20)
            assert [d["sequence"] for d in ros.wait_for(2, timeout_s=20)] == [0, 1]
            # As between rmw_zenoh's nodes on one host: the node and the camera are peers connected
            # directly (told of each other by the router), so images need not cross the router.
            peers = list(camera.info.peers_zid())
            assert len(peers) == 1 and str(peers[0]) != str(router.session.info.zid())
            plain.close()
            ros.sub.undeclare()

    summary = run_cli_while(drive, args, router, capsys)
    assert summary["frames_processed"] == 2 and summary["result_key"] == "robot/lcd"
    reader = McapLogReader(log_path)
    assert len(list(reader.frames())) == 2
    assert reader.metadata[RUN_CONFIG_METADATA]["ros"]["topic"] == TOPIC


def test_fuzzed_cdr_raises_only_frame_errors(typestore):
    """Flipped bytes anywhere (lengths included) in Image/CompressedImage CDR: FrameError or a frame."""
    rng = np.random.default_rng(20261122)
    gray = sample_images(1, size=(48, 32))[0]
    seeds = [(decode_image_cdr, ros_image(typestore, gray, "mono8", STAMP0)),
             (decode_image_cdr, ros_image(typestore, gray, "bgr8", STAMP0)),
             (decode_compressed_cdr, ros_compressed(typestore, gray, STAMP0))]
    refused = 0
    for i in range(600):
        decode, data = seeds[i % len(seeds)]
        buf = bytearray(data)
        head = min(len(buf), 96)  # mostly the header and length fields, where parsing decides
        for pos in rng.integers(0, head, int(rng.integers(1, 4))):
            buf[int(pos)] = int(rng.integers(0, 256))
        try:
            img = decode(bytes(buf))
            decode_frame(img.payload, img.encoding)
        except FrameError:
            refused += 1
    assert refused > 100  # the fuzz reaches the checks
