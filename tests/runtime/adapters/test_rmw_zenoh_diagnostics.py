"""ROS 2 health and identity of the node over rmw_zenoh: /diagnostics, gids, warnings.

The ROS side is written from rmw_zenoh's docs/design.md and sources, not from our adapter:
keys ``<domain>/<topic>/<type>/<hash>``, liveliness tokens under ``@ros2_lv``, the attachment
(int64 sequence number, int64 timestamp, 1-byte gid length, gid), gids as
liveliness_utils.cpp derives them (XXH3-128 of the token, low 64 bits then high 64 bits,
little-endian: here by the ``xxhash`` package), CDR decoded by rosbags.
"""

from __future__ import annotations

import json
import logging
import threading

import pytest
import zenoh

from aefabmap_runtime.adapters.rmw_zenoh import (
    DIAG_ERROR,
    DIAG_OK,
    DIAG_WARN,
    DIAGNOSTIC_ARRAY_RIHS01,
    IMAGE_RIHS01,
    STRING_RIHS01,
    RosOptions,
    RosResultPublisher,
    diagnostic_level,
)
from aefabmap_runtime.adapters.zenoh_transport import build_zenoh_config

from .stream_fakes import FakeDetector, NodeThread, sample_images
from .test_rmw_zenoh import STAMP0, TOPIC, Router, graph_tokens, rmw_attachment, ros_image

rosbags_typesys = pytest.importorskip("rosbags.typesys")
xxhash = pytest.importorskip("xxhash")
pytestmark = pytest.mark.timeout(90)

DOMAIN = 3
HASHES = {  # distro -> (image, String, DiagnosticArray) type hash chunks
    "jazzy": (IMAGE_RIHS01, STRING_RIHS01, DIAGNOSTIC_ARRAY_RIHS01),
    "humble": ("TypeHashNotSupported",) * 3,
}


def design_gid(token: str) -> bytes:
    """A gid as rmw_zenoh derives it from an entity's liveliness token."""
    return xxhash.xxh3_128_intdigest(token.encode()).to_bytes(16, "little")


def design_attachment(data: bytes) -> tuple[int, int, bytes]:
    """(sequence number, timestamp, gid) of an attachment laid out as design.md says."""
    n = data[16]
    assert len(data) == 17 + n
    return int.from_bytes(data[:8], "little", signed=True), int.from_bytes(data[8:16], "little", signed=True), \
        data[17:]


class Collector:
    """Samples of one key: (CDR payload, attachment bytes), with a condition to wait on."""

    def __init__(self, session, key: str) -> None:
        self.items: list[tuple[bytes, bytes]] = []
        self.cond = threading.Condition()

        def on_sample(sample) -> None:
            with self.cond:
                self.items.append((sample.payload.to_bytes(), sample.attachment.to_bytes()))
                self.cond.notify_all()

        self.sub = session.declare_subscriber(key, on_sample)

    def wait(self, predicate, timeout_s: float = 20) -> list[tuple[bytes, bytes]]:
        with self.cond:
            assert self.cond.wait_for(lambda: predicate(self.items), timeout_s), f"{len(self.items)} samples"
            return list(self.items)


def wait_matching(pub, timeout_s: float = 10) -> None:
    pause = threading.Event()
    for _ in range(int(timeout_s / 0.05)):
        if pub.matching_status.matching:
            return
        pause.wait(0.05)
    raise AssertionError("the node's subscription never matched")


@pytest.mark.parametrize("distro", ["jazzy", "humble"])
def test_camera_on_domain_3_gets_results_and_diagnostics_with_rmw_zenoh_gids(tmp_path, distro):
    """Node on defaults (distribution from the wire) in domain 3: every result reaches a
    subscriber of the camera's distribution, /diagnostics decodes as DiagnosticArray, the gids
    in the attachments are the ones derived from the node's tokens, one type per topic."""
    image_hash, string_hash, diag_hash = HASHES[distro]
    ts = rosbags_typesys.get_typestore(rosbags_typesys.Stores.ROS2_JAZZY if distro == "jazzy"
                                       else rosbags_typesys.Stores.ROS2_HUMBLE)
    router = Router()
    try:
        with (
            NodeThread(detector=FakeDetector(), session_config=router.ros_peer(), key="unused",
                       mcap_path=tmp_path / "ros.mcap", queue_size=16, stats_period_s=0.2,
                       ros=RosOptions(topic=TOPIC, domain=DOMAIN)) as node,
            zenoh.open(build_zenoh_config(router.ros_peer())) as camera,
        ):
            results = Collector(camera, f"{DOMAIN}/lcd/result/std_msgs::msg::dds_::String_/{string_hash}")
            stats = Collector(camera, f"{DOMAIN}/lcd/stats/std_msgs::msg::dds_::String_/{string_hash}")
            diags = Collector(camera, f"{DOMAIN}/diagnostics/diagnostic_msgs::msg::dds_::DiagnosticArray_/{diag_hash}")
            pub = camera.declare_publisher(f"{DOMAIN}/camera/image_raw/sensor_msgs::msg::dds_::Image_/{image_hash}",
                                           congestion_control=zenoh.CongestionControl.BLOCK)
            wait_matching(pub)
            n = 5
            for i, img in enumerate(sample_images(n, size=(160, 120))):
                pub.put(ros_image(ts, img, "mono8", STAMP0 + i), attachment=rmw_attachment(i + 1, STAMP0 + i))
            got = results.wait(lambda items: len(items) >= n)

            def done(items) -> bool:
                return any(_values(ts, p).get("frames_processed") == str(n) for p, _ in items)

            diag_items = diags.wait(done)
            tokens = graph_tokens(camera, DOMAIN)
            stat_items = stats.wait(lambda items: len(items) >= len(diag_items))
            node.finish()
    finally:
        router.close()

    docs = [json.loads(ts.deserialize_cdr(p, "std_msgs/msg/String").data) for p, _ in got]
    assert [d["sequence"] for d in docs] == list(range(n))
    ours = {t.split("/")[9]: t for t in tokens if t.split("/")[5] == "MP" and t.split("/")[8] == "aefabmap"}
    assert set(ours) == {"%lcd%result", "%lcd%stats", "%diagnostics"}
    for items, topic in ((got, "%lcd%result"), (diag_items, "%diagnostics"), (stat_items, "%lcd%stats")):
        atts = [design_attachment(a) for _, a in items]
        assert {gid for _, _, gid in atts} == {design_gid(ours[topic])}, topic
        assert [seq for seq, _, _ in atts] == list(range(1, len(atts) + 1))
    # One type per topic in the graph (the node's subscription names the camera's type and hash).
    types: dict[str, set[str]] = {}
    for t in tokens:
        parts = t.split("/")
        if len(parts) >= 13:
            types.setdefault(parts[9], set()).add(f"{parts[10]}/{parts[11]}")
    assert all(len(v) == 1 for v in types.values()), types
    # The DiagnosticArray: one status for the node, its stamp the stats message's.
    last = ts.deserialize_cdr(diag_items[-1][0], "diagnostic_msgs/msg/DiagnosticArray")
    assert len(last.status) == 1
    status = last.status[0]
    assert status.name == "aefabmap: aefabmap" and status.hardware_id and status.level == DIAG_OK
    values = {kv.key: kv.value for kv in status.values}
    assert values["frames_received"] == str(n) and values["dropped"] == "0" and values["log_state"] == "ok"
    assert values["places"] and "map_mb" in values and values["ros_distro"] == distro
    stamps = {json.loads(ts.deserialize_cdr(p, "std_msgs/msg/String").data)["stamp_ns"] for p, _ in stat_items}
    stamp = last.header.stamp.sec * 10**9 + last.header.stamp.nanosec
    assert stamp in stamps


def _values(ts, payload: bytes) -> dict[str, str]:
    msg = ts.deserialize_cdr(payload, "diagnostic_msgs/msg/DiagnosticArray")
    return {kv.key: kv.value for s in msg.status for kv in s.values}


class LogRecords(logging.Handler):
    """Records of one logger (whatever its propagation), with an event set on each."""

    def __init__(self, name: str) -> None:
        super().__init__(logging.WARNING)
        self.logger, self.messages, self.event = logging.getLogger(name), [], threading.Event()
        self.logger.addHandler(self)

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(record.getMessage())
        self.event.set()

    def close(self) -> None:
        self.logger.removeHandler(self)
        super().close()


def test_results_under_a_distro_no_subscriber_uses_are_warned_in_log_and_status(tmp_path):
    """--ros-distro jazzy while a Humble subscriber listens on /lcd/result: a warning in the log
    and in the node's status."""
    from aefabmap_runtime.adapters.health import find_runtimes, query_status

    logged = LogRecords("aefabmap.ros")
    router = Router()
    try:
        with (
            zenoh.open(build_zenoh_config(router.ros_peer())) as ros,
            NodeThread(detector=FakeDetector(), session_config=router.ros_peer(), key="unused",
                       mcap_path=tmp_path / "warn.mcap", stats_period_s=0.1,
                       ros=RosOptions(topic=TOPIC, domain=DOMAIN, distro="jazzy")) as node,
        ):
            # A Humble listener's subscription token, as rmw_zenoh declares it.
            token = ros.liveliness().declare_token(
                f"@ros2_lv/{DOMAIN}/{ros.info.zid()}/0/10/MS/%/%/listener/%lcd%result/"
                "std_msgs::msg::dds_::String_/TypeHashNotSupported/::,10:,:,:,,")
            pause, warnings = threading.Event(), []
            for _ in range(200):
                zids = find_runtimes(ros, 2.0)
                status = query_status(ros, zids, 2.0) if zids else {}
                warnings = [w for s in status.values() if not isinstance(s, str) for w in s.warnings]
                if warnings:
                    break
                pause.wait(0.05)
            assert logged.event.wait(10), "nothing logged"  # logged when the next stats go out
            token.undeclare()
            node.finish()
    finally:
        router.close()
        logged.close()
    assert any("/lcd/result" in w and "TypeHashNotSupported" in w for w in warnings), warnings
    assert any("/lcd/result" in m and "TypeHashNotSupported" in m for m in logged.messages), logged.messages


def test_a_result_before_the_distro_is_known_is_warned():
    router = Router()
    try:
        with zenoh.open(build_zenoh_config(router.ros_peer())) as session:
            pub = RosResultPublisher(session, "camera/lcd", RosOptions(topic=TOPIC), wire_distro=lambda: (None, None))
            try:
                assert pub.warnings() == []
                pub.publish_result({"sequence": 0})
                assert any("has not learnt" in w and "camera/lcd" in w for w in pub.warnings())
            finally:
                pub.close()
    finally:
        router.close()


def test_a_status_read_while_the_camera_teaches_the_distro_has_no_warning(monkeypatch):
    # The node's status thread may read warnings() while the frame thread publishes the first
    # result and adopts the camera's distribution: the result the camera's sample already taught
    # must not be warned about in between.
    router = Router()
    try:
        with zenoh.open(build_zenoh_config(router.ros_peer())) as session:
            pub = RosResultPublisher(session, "camera/lcd", RosOptions(topic=TOPIC),
                                     wire_distro=lambda: ("jazzy", "sensor_msgs/msg/Image"))
            read_meanwhile = []
            adopt = pub._adopt

            def adopt_while_read(*args):
                read_meanwhile.append(pub.warnings())
                adopt(*args)
                read_meanwhile.append(pub.warnings())

            monkeypatch.setattr(pub, "_adopt", adopt_while_read)
            try:
                pub.publish_result({"sequence": 0})
                assert read_meanwhile == [[], []] and pub.distro == "jazzy" and pub.warnings() == []
            finally:
                pub.close()
    finally:
        router.close()


def test_diagnostic_level_follows_drops_refusals_and_the_log():
    base = {"dropped": 2, "bad_total": 1, "log_state": "ok"}
    assert diagnostic_level(base, None)[0] == DIAG_WARN  # drops since the start
    assert diagnostic_level(base, base) == (DIAG_OK, "ok")
    assert diagnostic_level({**base, "bad_total": 3}, base)[0] == DIAG_WARN
    assert diagnostic_level({**base, "log_state": "images_stopped"}, base)[0] == DIAG_WARN
    assert diagnostic_level({**base, "log_state": "failed"}, base)[0] == DIAG_ERROR
