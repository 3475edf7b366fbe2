"""A node's liveliness token and status queryable on real loopback Zenoh sessions
(runtime/aefabmap_runtime/adapters/health.py)."""

from __future__ import annotations

import json
import queue
import time

import pytest
import zenoh

from aefabmap_runtime.adapters.health import (
    RUNTIME_TOKEN_PREFIX,
    find_runtimes,
    query_status,
    status_key,
    wait_for_peer,
)
from aefabmap_runtime.adapters.state_dir import bundle_id
from aefabmap_runtime.adapters.zenoh_transport import open_session
from aefabmap_runtime.core.records.json_schema import validate
from aefabmap_runtime.core.records.messages import MESSAGE_FORMAT_VERSION, StatusMessage
from aefabmap_runtime.tools.publisher import array_source, publish_frames

from .stream_fakes import (
    KEY,
    RESULTS,
    FakeDetector,
    JsonCollector,
    NodeThread,
    sample_images,
    session_pair,
)

pytestmark = pytest.mark.timeout(60)


def _wait_sample(q: queue.Queue, kind: zenoh.SampleKind, timeout_s: float) -> zenoh.Sample:
    while True:
        sample = q.get(timeout=timeout_s)  # queue.Empty fails the test
        if sample.kind == kind:
            return sample


def test_token_lives_while_the_node_runs(tmp_path):
    listen, connect = session_pair()
    with NodeThread(FakeDetector(), listen, key=KEY, mcap_path=tmp_path / "run.mcap") as node:
        watch = open_session(connect)
        samples: queue.Queue = queue.Queue()
        sub = watch.liveliness().declare_subscriber(f"{RUNTIME_TOKEN_PREFIX}/*", samples.put, history=True)
        appeared = _wait_sample(samples, zenoh.SampleKind.PUT, 10)
        zid = str(appeared.key_expr).rpartition("/")[2]
        assert find_runtimes(watch, 5) == [zid]
        node.finish()
        gone = _wait_sample(samples, zenoh.SampleKind.DELETE, 10)
        assert str(gone.key_expr) == str(appeared.key_expr)
        sub.undeclare()
        watch.close()


def test_status_answers_with_a_valid_message_after_frames(tmp_path):
    listen, connect = session_pair()
    detector = FakeDetector()
    with NodeThread(detector, listen, key=KEY, mcap_path=tmp_path / "run.mcap", queue_size=16) as node:
        watch = open_session(connect)
        assert wait_for_peer(watch, 10)
        results = JsonCollector(watch, RESULTS)
        pub = publish_frames(connect, KEY, array_source(sample_images(6), "jpeg"), rate_hz=100,
                             wait_for_subscriber_s=10)
        assert pub.published == 6
        results.wait_for(lambda d: d["frame_seq"] == 5, timeout_s=20)
        zids = find_runtimes(watch, 5)
        assert len(zids) == 1
        replies = list(watch.get(status_key(zids[0]), timeout=5))
        assert len(replies) == 1 and replies[0].ok is not None
        doc = json.loads(replies[0].ok.payload.to_bytes())
        assert validate(doc, StatusMessage.json_schema()) is None
        status = StatusMessage.from_json(doc)
        assert status.zid == zids[0] and status.results_key == RESULTS and status.image_key == KEY
        assert status.frames_received == status.frames_processed == 6 and status.bad_total == 0
        assert status.places == detector.places.__len__() and status.stage_ms.keys() == {"total"}
        assert status.recent_frames == 6 and status.uptime_s > 0
        assert status.log_files == 1 and status.log_bytes > 0 and status.log_state == "ok"
        assert status.bundle_id == bundle_id(detector.manifest)
        assert status.message_format_version == MESSAGE_FORMAT_VERSION
        assert query_status(watch, zids, 5)[zids[0]].frames_processed == 6
        results.close()
        watch.close()
        assert node.finish().frames_processed == 6


def test_hostile_queries_never_hurt_the_node(tmp_path):
    listen, connect = session_pair()
    with NodeThread(FakeDetector(), listen, key=KEY, mcap_path=tmp_path / "run.mcap", queue_size=16) as node:
        watch = open_session(connect)
        assert wait_for_peer(watch, 10)
        (zid,) = find_runtimes(watch, 5)
        hostile = [
            {"selector": f"{status_key(zid)}?;;;=&&x=%00%ff;_time=[..garbage]", "payload": b"\xff" * 65536},
            {"selector": "aefabmap/status/**", "payload": b"{\"frames\": -1}", "attachment": b"\x00" * 2048},
            {"selector": f"{status_key(zid)}?" + "k=v;" * 2000, "encoding": zenoh.Encoding.APPLICATION_JSON},
        ]
        handlers = [watch.get(timeout=5, **h) for h in hostile for _ in range(20)]
        answers = [r for h in handlers for r in h]
        assert answers and all(r.ok is not None for r in answers)
        assert all(StatusMessage.from_json(r.ok.payload.to_bytes()).zid == zid for r in answers)
        pub = publish_frames(connect, KEY, array_source(sample_images(4), "jpeg"), rate_hz=100,
                             wait_for_subscriber_s=10)
        assert pub.published == 4
        (after,) = query_status(watch, [zid], 5).values()
        watch.close()
        summary = node.finish()
    assert summary.frames_processed == 4
    assert not isinstance(after, str) and after.frames_received <= 4


def test_no_runtime_gives_an_empty_list():
    listen, connect = session_pair()
    peer = open_session(listen)
    watch = open_session(connect)
    assert wait_for_peer(watch, 10)
    assert find_runtimes(watch, 1) == []
    assert query_status(watch, ["0123456789abcdef"], 0.5) == {"0123456789abcdef": "no answer"}
    watch.close()
    peer.close()


def test_status_does_not_wait_for_a_slow_frame(tmp_path):
    listen, connect = session_pair()
    with NodeThread(FakeDetector(delay_s=1.5), listen, key=KEY, mcap_path=tmp_path / "run.mcap") as node:
        watch = open_session(connect)
        assert wait_for_peer(watch, 10)
        (zid,) = find_runtimes(watch, 5)
        pub = publish_frames(connect, KEY, array_source(sample_images(1), "jpeg"), rate_hz=100,
                             wait_for_subscriber_s=10)
        assert pub.published == 1
        t0 = time.monotonic()
        (status,) = query_status(watch, [zid], 5).values()
        elapsed_s = time.monotonic() - t0
        watch.close()
        node.finish()
    assert not isinstance(status, str) and status.frames_processed == 0  # the frame was in the detector (or not yet taken)
    assert elapsed_s < 0.5


def test_peak_rss_is_the_kernels_high_water_mark_not_a_sample():
    """A short allocation between two samples is still in the peak (it was missed when the
    peak was the largest 5-s sample)."""
    import numpy as np

    from aefabmap_runtime.adapters.health import peak_rss_mb, rss_mb

    before = rss_mb()
    block = np.ones(300 * 2**20 // 8)  # 300 MB touched, then freed
    del block
    peak = peak_rss_mb()
    assert peak is not None and before is not None
    assert peak >= before + 250 and rss_mb() < peak
