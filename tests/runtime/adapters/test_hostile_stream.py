"""A hostile peer on the Zenoh stream: attachments are untrusted, out-of-range times never
reach the MCAP writer, and the node keeps running with a readable log."""

from __future__ import annotations

import json
import time

import pytest
import zenoh

from aefabmap.errors import LogError
from aefabmap.runtime.adapters.frames import encode_frame
from aefabmap.runtime.adapters.mcap_log import McapLogReader, McapLogWriter
from aefabmap.runtime.adapters.zenoh_transport import (
    MAX_ATTACHMENT_BYTES,
    DropCounter,
    FrameMeta,
    FramePublisher,
    open_session,
)

from .stream_fakes import (
    FakeDetector,
    JsonCollector,
    NodeThread,
    sample_images,
    session_pair,
)

pytestmark = pytest.mark.timeout(90)
KEY = "robot/camera/image"
RESULTS = "robot/camera/lcd"
STATS = "robot/camera/lcd/stats"

#: Attachments a hostile or broken publisher may send; each must be refused (counted).
HOSTILE_ATTACHMENTS = [
    b'{"seq": 0, "stamp_ns": -5, "src": "x"}',
    json.dumps({"seq": 1, "stamp_ns": 2**64, "src": "x"}).encode(),
    json.dumps({"seq": 2, "stamp_ns": 10**400, "src": "x"}).encode(),
    b'{"seq": 3, "stamp_ns": 1e30, "src": "x"}',
    b'{"seq": 4, "stamp_ns": NaN, "src": "x"}',
    b'{"seq": 5, "stamp_ns": "1700000000000000000", "src": "x"}',
    b'{"seq": true, "src": "x"}',
    b'{"seq": -1, "src": "x"}',
    json.dumps({"seq": 2**70, "src": "x"}).encode(),
    b'{"seq": 6, "src": ["not", "a", "string"]}',
    json.dumps({"seq": 7, "src": "s" * 500}).encode(),
    json.dumps({"seq": 8, "src": "s" * (MAX_ATTACHMENT_BYTES + 1)}).encode(),
    b"\xff\xfe not utf-8",
    b"not json at all",
    b"[1, 2, 3]",
    b"42",
    b"[" * 1000,  # nesting deeper than the JSON parser's recursion limit
    b"1" * 5000,  # an integer too long to convert
]


@pytest.mark.parametrize("attachment", HOSTILE_ATTACHMENTS, ids=range(len(HOSTILE_ATTACHMENTS)))
def test_hostile_attachment_is_refused_and_reported(attachment):
    meta = FrameMeta.from_attachment(attachment)
    assert meta.problem
    assert meta.stamp_ns is None or 0 <= meta.stamp_ns < 2**63
    assert meta.seq is None or 0 <= meta.seq < 2**63
    assert isinstance(meta.src, str) and len(meta.src) <= 64


def test_good_and_absent_attachments_have_no_problem():
    good = FrameMeta(seq=3, stamp_ns=42, src="cam")
    assert FrameMeta.from_attachment(good.to_attachment()) == good
    assert not FrameMeta.from_attachment(good.to_attachment()).problem
    assert not FrameMeta.from_attachment(None).problem
    assert not FrameMeta.from_attachment(FrameMeta().to_attachment()).problem  # all null: unsequenced
    # the fields that are fine are kept when another one is refused
    mixed = FrameMeta.from_attachment(b'{"seq": 9, "stamp_ns": -5, "src": "cam"}')
    assert (mixed.seq, mixed.stamp_ns, mixed.src) == (9, None, "cam") and "stamp_ns" in mixed.problem


def test_drop_counter_tracks_a_bounded_number_of_sources():
    c = DropCounter()
    for i in range(10 * DropCounter.MAX_SOURCES):
        c.update(FrameMeta(seq=0, src=f"src{i}"))
    assert len(c._last) == DropCounter.MAX_SOURCES
    assert c.dropped == 0 and c.restarts == 0


@pytest.mark.parametrize("stamp", [-5, 2**64, 2**70])
def test_mcap_writer_refuses_out_of_range_times_and_the_log_stays_readable(tmp_path, stamp):
    path = tmp_path / "t.mcap"
    payload, enc = encode_frame(sample_images(1, size=(64, 48))[0], "jpeg")
    with McapLogWriter(path) as log:
        log.write_image(payload, enc, 1_000, sequence=0)
        with pytest.raises(LogError, match="time"):
            log.write_image(payload, enc, stamp, sequence=1)
        with pytest.raises(LogError, match="time"):
            log.write_result({"sequence": 1, "stamp_ns": stamp})
        with pytest.raises(LogError, match="time"):
            log.write_stats({"frames": 1}, log_time_ns=stamp)
        log.write_image(payload, enc, 2_000, sequence=2)
    reader = McapLogReader(path)
    frames = list(reader.frames())
    assert not reader.status.truncated
    assert [f.stamp_ns for f in frames] == [1_000, 2_000]


def test_node_survives_hostile_attachments_and_falls_back_to_receive_time(tmp_path):
    listen, connect = session_pair()
    log_path = tmp_path / "hostile.mcap"
    payload, enc = encode_frame(sample_images(1, size=(64, 48))[0], "jpeg")
    n_bad = len(HOSTILE_ATTACHMENTS)
    with NodeThread(detector=FakeDetector(threshold=-1.0), session_config=listen, key=KEY, mcap_path=log_path,
                    queue_size=64, stats_period_s=0.2) as node:
        with open_session(connect) as s:
            results = JsonCollector(s, RESULTS)
            stats = JsonCollector(s, STATS)
            probe = FramePublisher(s, KEY, congestion="block")
            assert probe.wait_for_subscriber(10)
            raw = s.declare_publisher(KEY, congestion_control=zenoh.CongestionControl.BLOCK)
            t_before = time.time_ns()
            for att in HOSTILE_ATTACHMENTS:
                raw.put(payload, encoding=zenoh.Encoding(enc), attachment=att)
            probe.put(payload, enc, stamp_ns=1_700_000_000_000_000_000)  # one good frame last
            docs = results.wait_for(lambda d: d["sequence"] == n_bad, timeout_s=20)
            t_after = time.time_ns()
            stat = stats.wait_for(lambda d: d["bad"].get("bad_attachment") == n_bad, timeout_s=20)[-1]
            assert node.thread.is_alive()
            raw.undeclare()
            probe.close()
            results.close()
            stats.close()
        summary = node.finish()
    assert [d["sequence"] for d in docs] == list(range(n_bad + 1))
    assert all(t_before <= d["stamp_ns"] <= t_after for d in docs[:n_bad])  # receive time
    assert docs[-1]["stamp_ns"] == 1_700_000_000_000_000_000
    assert stat["frames_processed"] == n_bad + 1
    assert summary.bad["bad_attachment"] == n_bad and summary.frames_processed == n_bad + 1
    reader = McapLogReader(log_path)
    frames = list(reader.frames())
    assert not reader.status.truncated and len(frames) == n_bad + 1
    assert [f.stamp_ns for f in frames] == [d["stamp_ns"] for d in docs]
