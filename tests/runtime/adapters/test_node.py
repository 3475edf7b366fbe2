"""Streaming node and publisher on real loopback Zenoh sessions (runtime/aefabmap_runtime/adapters/node.py)."""

from __future__ import annotations

import argparse
import os
import signal
import threading
import time

import numpy as np
import pytest

from aefabmap_runtime.errors import LogError
from aefabmap_runtime.adapters.frames import encode_frame
from aefabmap_runtime.adapters.mcap_log import (
    MANIFEST_METADATA,
    RUN_CONFIG_METADATA,
    McapLogReader,
)
from aefabmap_runtime.adapters.node import NodeOptions, rss_mb, run_node, stop_on_signals
from aefabmap_runtime.adapters.zenoh_transport import FramePublisher, open_session
from aefabmap_runtime.tools.publisher import (
    array_source,
    images_dir_source,
    publish_frames,
)
from aefabmap_runtime.tools.synthetic_route import write_sequence

from .stream_fakes import (
    CLI,
    KEY,
    RESULTS,
    STATS,
    FakeDetector,
    JsonCollector,
    NodeThread,
    sample_images,
    run_node_process,
    session_pair,
)

pytestmark = pytest.mark.timeout(90)


def test_end_to_end_publish_detect_log(tmp_path):
    listen, connect = session_pair()
    log_path = tmp_path / "run.mcap"
    images = sample_images(12, size=(160, 120))
    with NodeThread(detector=FakeDetector(), session_config=listen, key=KEY, mcap_path=log_path,
                    queue_size=16, stats_period_s=0.2, image_log_every=1, run_config={"model": "fake"}) as node:
        watch = open_session(connect)
        results = JsonCollector(watch, RESULTS)
        stats = JsonCollector(watch, STATS)
        pub = publish_frames(connect, KEY, array_source(images, "jpeg"), rate_hz=100, wait_for_subscriber_s=10)
        assert pub.published == 12 and pub.matched
        docs = results.wait_for(lambda d: d["frame_seq"] == 11, timeout_s=20)
        stats.wait_for(lambda d: d["frames_processed"] == 12, timeout_s=20)
        summary = node.finish()
        results.close()
        stats.close()
        watch.close()
    assert summary.frames_processed == 12 and summary.dropped == 0 and summary.bad_total == 0
    assert [d["sequence"] for d in docs] == list(range(12))
    assert all(d["latency_ms"] >= 0 and "timings_ms" in d for d in docs)
    assert summary.latency_ms_p50 is not None and summary.latency_ms_p95 >= summary.latency_ms_p50
    assert summary.result_key == RESULTS and summary.images_logged == 12
    reader = McapLogReader(log_path)
    frames = list(reader.frames())
    assert not reader.status.truncated
    assert len(frames) == 12 and [r.sequence for r in reader.results] == list(range(12))
    assert [f.stamp_ns for f in frames] == [r.stamp_ns for r in reader.results]
    assert reader.stats and reader.stats[-1].frames_processed == 12
    assert reader.metadata[MANIFEST_METADATA]["detector"] == "fake"
    assert reader.metadata[RUN_CONFIG_METADATA]["model"] == "fake"
    assert reader.metadata[RUN_CONFIG_METADATA]["key"] == KEY


def _jpeg_header_50mp() -> bytes:
    sof = b"\xff\xc0\x00\x11\x08" + (6250).to_bytes(2, "big") + (8000).to_bytes(2, "big") + b"\x03" + b"\x00" * 9
    return b"\xff\xd8" + sof + b"\x00" * 64


def test_bad_frames_are_counted_per_reason_and_the_loop_goes_on(tmp_path):
    listen, connect = session_pair()
    good, genc = encode_frame(sample_images(1, size=(64, 48))[0], "jpeg")
    bad_frames = [
        (good[:60], "image/jpeg", "corrupt"),
        (b"", "image/jpeg", "empty"),
        (good, "text/plain", "wrong_encoding"),
        (b"\x00" * 99, "mono8;10x10", "size_mismatch"),
        (_jpeg_header_50mp(), "image/jpeg", "too_large"),
        (b"hello, I am not an image", "image/png", "not_image"),
        (b"\x00" * 16, "mono8;4x4", "rejected"),  # decodes, but the detector refuses 4x4
    ]
    with NodeThread(detector=FakeDetector(), session_config=listen, key=KEY, mcap_path=tmp_path / "bad.mcap",
                    queue_size=32, stats_period_s=0.2) as node:
        with open_session(connect) as s:
            results = JsonCollector(s, RESULTS)
            stats = JsonCollector(s, STATS)
            pub = FramePublisher(s, KEY, congestion="block")
            assert pub.wait_for_subscriber(10)
            for payload, enc, _ in bad_frames:
                pub.put(payload, enc)
            pub.put(good, genc)
            docs = results.wait_for(lambda d: True, timeout_s=20)
            assert docs[0]["frame_seq"] == len(bad_frames)
            stat = stats.wait_for(lambda d: d["bad_total"] == len(bad_frames), timeout_s=20)[-1]
            pub.close()
            results.close()
            stats.close()
        summary = node.finish()
    expected = {reason: 1 for _, _, reason in bad_frames}
    assert {k: v for k, v in summary.bad.items() if v} == expected
    assert {k: v for k, v in stat["bad"].items() if v} == expected
    assert stat["rss_mb"] is None or stat["rss_mb"] > 10
    assert summary.frames_processed == 1 and summary.frames_received == len(bad_frames) + 1


def test_publisher_vanishing_mid_stream(tmp_path):
    listen, connect = session_pair()
    images = sample_images(8, size=(64, 48))
    with NodeThread(detector=FakeDetector(), session_config=listen, key=KEY, mcap_path=tmp_path / "v.mcap",
                    queue_size=16, stats_period_s=0.2) as node:
        watch = open_session(connect)
        results = JsonCollector(watch, RESULTS)
        # first publisher: a whole session that goes away after 4 frames
        first = publish_frames(connect, KEY, array_source(images[:4]), rate_hz=200, wait_for_subscriber_s=10)
        assert first.published == 4
        results.wait_for(lambda d: d["sequence"] == 3, timeout_s=20)
        # the node is still alive and serves a new publisher (its seq restarts at 0)
        second = publish_frames(connect, KEY, array_source(images[4:]), rate_hz=200, wait_for_subscriber_s=10)
        assert second.published == 4
        results.wait_for(lambda d: d["sequence"] == 7, timeout_s=20)
        assert node.thread.is_alive()
        summary = node.finish()
        results.close()
        watch.close()
    assert summary.frames_processed == 8 and summary.dropped == 0 and summary.bad_total == 0


def test_slow_detector_drops_old_frames_and_counts_them(tmp_path):
    listen, connect = session_pair()
    n = 30
    with NodeThread(detector=FakeDetector(delay_s=0.03), session_config=listen, key=KEY,
                    mcap_path=tmp_path / "slow.mcap", queue_size=1, stats_period_s=0.5) as node:
        with open_session(connect) as s:
            results = JsonCollector(s, RESULTS)
            src = array_source(sample_images(n, size=(64, 48)))
            publish_frames(connect, KEY, src, rate_hz=500, wait_for_subscriber_s=10)
            docs = results.wait_for(lambda d: d["frame_seq"] == n - 1, timeout_s=30)
            results.close()
        summary = node.finish()
    assert summary.dropped > 0
    assert summary.frames_processed + summary.dropped + docs[0]["frame_seq"] == n
    assert len(docs) == summary.frames_processed


def test_unwritable_mcap_fails_before_opening_the_session(tmp_path):
    listen, _ = session_pair()
    with pytest.raises(LogError, match="nowhere"):
        run_node(FakeDetector(), NodeOptions(KEY, tmp_path / "nowhere" / "x.mcap", listen), stop_event=threading.Event())


def test_stop_event_ends_an_idle_node_cleanly(tmp_path):
    listen, _ = session_pair()
    log_path = tmp_path / "idle.mcap"
    with NodeThread(detector=FakeDetector(), session_config=listen, key=KEY, mcap_path=log_path,
                    stats_period_s=60) as node:
        summary = node.finish(timeout_s=5)
    assert summary.frames_received == 0
    r = McapLogReader(log_path)
    list(r.frames())
    assert not r.status.truncated and len(r.stats) == 1  # the final stats


def test_publish_rate_count_loop_and_images_dir(tmp_path):
    listen, connect = session_pair()
    images = sample_images(4, size=(64, 48))
    write_sequence(tmp_path / "seq", images, np.zeros((4, 4), bool))
    src = images_dir_source(tmp_path / "seq")
    assert [enc for _, enc in src()] == ["image/jpeg"] * 4
    with open_session(listen) as s:
        sub = s.declare_subscriber(KEY, lambda sample: None)
        t0 = time.monotonic()
        summary = publish_frames(connect, KEY, src, rate_hz=40, count=10, loop=True, wait_for_subscriber_s=10)
        elapsed = time.monotonic() - t0
        sub.undeclare()
    assert summary.published == 10 and summary.matched
    assert elapsed >= 9 / 40 * 0.9
    with pytest.raises(Exception):
        images_dir_source(tmp_path / "missing")
    stop = threading.Event()
    stop.set()
    stopped = publish_frames(connect, KEY, src, rate_hz=1, loop=True, stop_event=stop, wait_for_subscriber_s=0)
    assert stopped.published == 0


def test_sigterm_sets_the_stop_event():
    stop = threading.Event()
    before = signal.getsignal(signal.SIGTERM)
    with stop_on_signals(stop):
        os.kill(os.getpid(), signal.SIGTERM)
        assert stop.wait(5)
    assert signal.getsignal(signal.SIGTERM) is before


# The main thread holds the stop event's internal lock while it enters and leaves Event.wait
# (the node's receive loop waits on it many times a second). A handler that called
# Event.set() itself would, when the signal lands in that window, wait forever for a lock
# its own thread holds: `run` hung on SIGTERM once in CI this way. Run in a child process
# so that the old behaviour fails by timeout instead of hanging the suite.
_SIGNAL_IN_WAIT_WINDOW = """
import os, signal, threading
from aefabmap_runtime.adapters.node import stop_on_signals
stop = threading.Event()
with stop_on_signals(stop):
    with stop._cond:  # the state of the main thread inside Event.wait's prologue / epilogue
        os.kill(os.getpid(), signal.SIGTERM)
        for _ in range(1000):  # bytecodes: the handler runs here, with the lock held
            pass
    assert stop.wait(5), "the stop event was never set"
print("stopped")
"""


def test_sigterm_while_the_main_thread_holds_the_stop_events_lock_does_not_deadlock():
    import subprocess
    import sys

    try:
        proc = subprocess.run([sys.executable, "-c", _SIGNAL_IN_WAIT_WINDOW], capture_output=True, text=True,
                              timeout=20, check=False)
    except subprocess.TimeoutExpired:
        pytest.fail("the signal handler deadlocked on the stop event's lock")
    assert proc.returncode == 0 and proc.stdout.strip() == "stopped", proc.stderr


def test_rss_is_measured():
    value = rss_mb()
    assert value is None or 5 < value < 10_000


def test_cli_options_parse():
    from aefabmap.cli import options, publish, replay, run

    parser = argparse.ArgumentParser(prog="aefabmap")
    subparsers = parser.add_subparsers(dest="command")
    for module in (run, publish, replay):
        module.register(subparsers)
    a = parser.parse_args(
        "run --model B --key k/img --connect tcp/127.0.0.1:7447 --listen tcp/127.0.0.1:7448 --config z.json5 "
        "--mcap L.mcap --max-places 100 --memory-mb 64 --queue 3 --image-every 2".split()
    )
    assert (a.model, a.key, a.connect, a.listen, a.config, a.mcap) == (
        "B", "k/img", ["tcp/127.0.0.1:7447"], ["tcp/127.0.0.1:7448"], "z.json5", "L.mcap")
    assert (a.max_places, a.memory_mb, a.queue, a.image_every, a.func) == (100, 64.0, 3, 2, run.main)
    p = parser.parse_args("publish --images D --key k --rate 10 --loop --count 5".split())
    assert (p.images, p.video, p.camera, p.rate, p.loop, p.count, p.func) == ("D", None, None, 10.0, True, 5,
                                                                             publish.main)
    with pytest.raises(SystemExit):
        parser.parse_args("publish --images D --video V --key k --rate 10".split())
    r = parser.parse_args("replay L.mcap --model B --out N.mcap --check".split())
    assert (r.log, r.model, r.out, r.check, r.func) == (["L.mcap"], "B", "N.mcap", True, replay.main)
    r = parser.parse_args("replay A.mcap logs/ --model B".split())
    assert r.log == ["A.mcap", "logs/"]
    a = parser.parse_args("run --model B --key k --mcap logs/ --mcap-max-mb 5 --log-budget-mb 20".split())
    assert (a.mcap, a.mcap_max_mb, a.log_budget_mb, a.log_min_free_mb) == ("logs/", 5.0, 20.0, None)
    rotation = options.log_rotation_config(a)
    assert (rotation.max_mb, rotation.budget_mb, rotation.images_threshold_bytes) == (5.0, 20.0, 500 * 2**20)
    a = parser.parse_args("run --model B --key k --mcap L.mcap --log-min-free-mb 50 10".split())
    assert (options.log_rotation_config(a).images_min_free_mb, options.log_rotation_config(a).results_min_free_mb) == (50, 10)


def test_cli_run_stops_on_sigint_with_a_finished_log(tmp_path, monkeypatch):
    """`aefabmap run` main(): SIGINT (from another thread) stops it; exit 0; log complete."""
    import aefabmap_runtime.adapters.bundle_reader as bundle_reader_mod
    from aefabmap.cli import run

    monkeypatch.setattr(bundle_reader_mod, "load_detector", lambda *a, **k: FakeDetector())
    listen, connect = session_pair()
    log_path = tmp_path / "cli.mcap"
    from aefabmap.cli.main import build_parser

    args = build_parser().parse_args(["run", "--model", "fake", "--key", KEY, "--mcap", str(log_path), "--queue", "4",
                                      *(f"--listen={ep}" for ep in listen.listen)])
    got = threading.Event()
    errors = []

    def drive() -> None:
        try:
            # The node may not listen yet: a peer session retries its connect in the
            # background, so wait until our publisher matches the node's subscriber.
            with open_session(connect) as s:
                results = JsonCollector(s, RESULTS)
                pub = FramePublisher(s, KEY, congestion="block")
                assert pub.wait_for_subscriber(30)
                for img in sample_images(3, size=(64, 48)):
                    pub.put(*encode_frame(img, "jpeg"))
                results.wait_for(lambda d: d["sequence"] == 2, timeout_s=20)
                pub.close()
                results.close()
            got.set()
        except BaseException as exc:
            errors.append(exc)
        finally:
            os.kill(os.getpid(), signal.SIGINT)

    driver = threading.Thread(target=drive, daemon=True)
    driver.start()
    code = run.main(args)
    driver.join(10)
    assert not errors and got.is_set()
    assert code == 0
    r = McapLogReader(log_path)
    assert len(list(r.frames())) == 3 and not r.status.truncated


@pytest.mark.slow
@pytest.mark.timeout(180)
def test_cli_processes_run_publish_replay_with_a_real_bundle(tmp_path):
    """`aefabmap run` and `aefabmap publish` as processes; SIGTERM stops run; replay --check passes."""
    import json
    import subprocess

    from aefabmap_runtime.tools.synthetic_route import make_demo_sequence
    from tests.conftest import make_synthetic_bundle

    bundle = make_synthetic_bundle(tmp_path / "bundle")
    make_demo_sequence(tmp_path / "seq", n_frames=16, seed=2, size=(160, 120))
    log_path = tmp_path / "run.mcap"
    node = run_node_process(["--model", str(bundle), "--mcap", str(log_path), "--queue", "32"], tmp_path / "seq",
                            15, rate=50, timeout_s=60)
    assert json.loads(node.published.strip().splitlines()[-1])["published"] == 16
    assert node.returncode == 0, node.stderr
    assert json.loads(node.stdout.strip().splitlines()[-1])["frames_processed"] == 16
    rep = subprocess.run(CLI + ["replay", str(log_path), "--model", str(bundle), "--check", "--out",
                                str(tmp_path / "re.mcap")], capture_output=True, text=True, timeout=120)
    assert rep.returncode == 0, rep.stderr
    assert json.loads(rep.stdout.strip().splitlines()[-1])["check"]["compared"] == 16


@pytest.mark.slow
@pytest.mark.timeout(240)
def test_replay_check_reproduces_a_run_with_non_default_settings(tmp_path):
    """The whole run configuration goes into the log: a replay with the camera, exclusion window and
    candidate count of the run decides every frame as the run did (a replay with the defaults differs)."""
    import json
    import subprocess

    from aefabmap_runtime.adapters.mcap_log import RUN_CONFIG_METADATA, read_log_metadata
    from aefabmap_runtime.tools.synthetic_route import make_demo_sequence
    from tests.conftest import make_synthetic_bundle

    bundle = make_synthetic_bundle(tmp_path / "bundle")
    make_demo_sequence(tmp_path / "seq", n_frames=40, seed=3, size=(320, 240))
    log_path = tmp_path / "run.mcap"
    options = ["--exclude", "5", "--camera", "250,250,160,120", "--verify-top-k", "3", "--memory-mb", "32"]
    node = run_node_process(["--model", str(bundle), "--mcap", str(log_path), "--queue", "64", *options],
                            tmp_path / "seq", 39, rate=40, timeout_s=120)
    assert node.returncode == 0, node.stderr
    logged = read_log_metadata(log_path)[RUN_CONFIG_METADATA]["run"]
    assert logged["detector"]["exclude"] == 5 and logged["detector"]["verification"]["camera"] == [250, 250, 160, 120]
    assert logged["detector"]["candidates"]["top_k"] == 3
    rep = subprocess.run(CLI + ["replay", str(log_path), "--model", str(bundle), "--check"],
                         capture_output=True, text=True, timeout=120)
    assert rep.returncode == 0, rep.stderr
    check = json.loads(rep.stdout.strip().splitlines()[-1])["check"]
    assert check["compared"] == 40 and check["matched"] == 40 and check["ok"]


def test_a_result_goes_out_only_once_its_frame_is_in_the_map_journal(tmp_path, monkeypatch):
    """The attack: a result was published before its frame reached the map journal, so a kill -9
    between the two made the restarted node reuse a sequence number that had gone out. Watched at
    the two boundaries: the journal's write to its file and the result publisher."""
    import json
    import logging
    import struct

    from aefabmap.cli.options import default_bundle
    from aefabmap_runtime.adapters import map_journal
    from aefabmap_runtime.adapters.bundle_reader import load_detector
    from aefabmap_runtime.adapters.node_state import NodeState
    from aefabmap_runtime.adapters.state_dir import SnapshotPolicy
    from aefabmap_runtime.adapters.zenoh_transport import ResultPublisher
    from aefabmap_runtime.core.detector import DetectorConfig

    events: list[tuple[str, int]] = []
    real_write, real_publish = map_journal._os_write, ResultPublisher.publish_result

    def write(fd, data):
        data = bytes(data)
        if data[8:9] == b"F":  # a frame record: u32 length, u32 crc, b"F", i64 sequence
            events.append(("journal", struct.unpack_from("<q", data, 9)[0]))
        return real_write(fd, data)

    def publish(self, data):
        events.append(("publish", json.loads(data)["sequence"]))
        return real_publish(self, data)

    monkeypatch.setattr(map_journal, "_os_write", write)
    monkeypatch.setattr(ResultPublisher, "publish_result", publish)
    detector = load_detector(default_bundle(), DetectorConfig(exclude=2))
    state = NodeState(tmp_path / "state", detector, SnapshotPolicy(seconds=None, places=1000),
                      logging.getLogger("test.node"))
    listen, connect = session_pair()
    try:
        with NodeThread(detector=detector, session_config=listen, key=KEY, mcap_path=tmp_path / "run.mcap",
                        queue_size=16, snapshotter=state.snapshotter) as node:
            with open_session(connect) as s:
                results = JsonCollector(s, RESULTS)
                publish_frames(connect, KEY, array_source(sample_images(6, size=(160, 120)), "jpeg"), rate_hz=50,
                               wait_for_subscriber_s=10)
                results.wait_for(lambda d: d["sequence"] == 5, timeout_s=30)
                results.close()
            node.finish()
    finally:
        state.close()
    published = [seq for kind, seq in events if kind == "publish"]
    assert published == list(range(6))
    for seq in published:
        assert events.index(("journal", seq)) < events.index(("publish", seq)), events


@pytest.mark.slow
@pytest.mark.timeout(240)
def test_a_node_killed_right_after_a_result_never_reuses_a_published_sequence(tmp_path):
    """`aefabmap run --state` as a process, killed (SIGKILL, from the result subscriber's callback)
    as soon as a result arrives; the restarted node's first result takes the next sequence number.
    Frames go one at a time, each after the previous result, so every result published was seen."""
    import json
    import subprocess

    from aefabmap.cli.options import default_bundle

    images = sample_images(6, size=(640, 480))  # raw frames: the log stores them as PNG, which takes a while
    state = tmp_path / "state"

    def start(log: str):
        listen, connect = session_pair()
        run = subprocess.Popen(CLI + ["run", "--model", str(default_bundle()), "--key", KEY, "--listen",
                                      listen.listen[0], "--mcap", str(tmp_path / log), "--state", str(state),
                                      "--snapshot-every", "1000p", "--queue", "8"],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        return run, connect

    def feed(run, connect, frames, *, kill_after: int | None = None) -> list[int]:
        """Publish `frames` one at a time; the sequences of their results (the node is killed in
        the callback of result number kill_after)."""
        got: list[int] = []
        arrived = threading.Event()

        def on_result(sample) -> None:
            got.append(json.loads(sample.payload.to_bytes())["sequence"])
            if kill_after is not None and len(got) == kill_after:
                run.kill()
            arrived.set()

        with open_session(connect) as s:
            sub = s.declare_subscriber(RESULTS, on_result)
            pub = FramePublisher(s, KEY, congestion="block")
            assert pub.wait_for_subscriber(90), "the node never subscribed"
            for img in frames:
                arrived.clear()
                pub.put(*encode_frame(img, "mono8"))
                assert arrived.wait(60), f"no result after {got}"
            pub.close()
            sub.undeclare()
        return got

    run, connect = start("first.mcap")
    try:
        published = feed(run, connect, images[:4], kill_after=4)
        assert run.wait(30) == -signal.SIGKILL
    finally:
        if run.poll() is None:
            run.kill()
            run.wait(10)
    assert published == [0, 1, 2, 3]

    run, connect = start("second.mcap")
    try:
        restarted = feed(run, connect, images[4:])
        run.send_signal(signal.SIGTERM)
        _out, err = run.communicate(timeout=60)
    finally:
        if run.poll() is None:
            run.kill()
            run.wait(10)
    assert run.returncode == 0, err
    assert restarted == [4, 5], f"the restarted node reused a published sequence: {restarted}"
