"""Replay and --check (runtime/aefabmap_runtime/adapters/replay.py) on live logs, truncated logs and ROS 2 bags."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from aefabmap_runtime.errors import LogError
from aefabmap_runtime.adapters.mcap_log import (
    McapLogConfig,
    McapLogReader,
    McapLogWriter,
)
from aefabmap_runtime.adapters.replay import (
    NONDETERMINISTIC_FIELDS,
    compare_results,
    replay,
)
from aefabmap_runtime.adapters.ros_bag import rosbags_available
from aefabmap_runtime.adapters.zenoh_transport import open_session
from aefabmap_runtime.tools.publisher import array_source, publish_frames

from .stream_fakes import (
    KEY,
    FakeDetector,
    JsonCollector,
    NodeThread,
    record_live_log,
    sample_images,
    session_pair,
    write_ros2_bag,
)
from tests.conftest import cli_args

pytestmark = pytest.mark.timeout(90)


@pytest.fixture(scope="module")
def live_log(tmp_path_factory):
    """A log recorded by the live node: 16 frames of a two-lap synthetic loop (jpeg + raw)."""
    path = tmp_path_factory.mktemp("live") / "live.mcap"
    summary, _ = record_live_log(path, stats_period_s=0.5)
    assert summary.frames_processed == 16
    return path


def test_replay_of_a_live_log_checks_ok_and_writes_a_new_log(live_log, tmp_path):
    out = tmp_path / "replayed.mcap"
    summary = replay(FakeDetector(), live_log, out_path=out, check=True)
    assert summary.frames_read == 16 and summary.frames_processed == 16
    assert summary.check is not None and summary.check.ok, summary.check.describe()
    assert summary.check.compared == 16 and summary.check.complete
    assert summary.loops > 0  # the second lap revisits the first
    assert "check OK" in summary.check.describe()
    json.dumps(summary.to_dict(), default=str)
    # the new log replays to the same results again
    again = replay(FakeDetector(), out, check=True)
    assert again.check.ok and again.check.compared == 16
    # A second replay into the same --out never overwrites the first: it writes beside it.
    before = out.read_bytes()
    second = replay(FakeDetector(), live_log, out_path=out)
    assert second.out_path == str(tmp_path / "replayed-0001.mcap") and out.read_bytes() == before
    assert replay(FakeDetector(), second.out_path, check=True).check.ok


def test_replay_out_into_a_missing_directory_creates_it(live_log, tmp_path):
    out_dir = tmp_path / "new" / "logs"
    summary = replay(FakeDetector(), live_log, out_path=f"{out_dir}/")
    assert out_dir.is_dir() and summary.out_path is not None and Path(summary.out_path).parent == out_dir
    assert replay(FakeDetector(), summary.out_path, check=True).check.ok


def test_check_reports_differences(live_log):
    summary = replay(FakeDetector(threshold=0.5), live_log, check=True)
    report = summary.check
    assert not report.ok and report.mismatched > 0
    assert "loop" in report.field_counts or "inserted_place" in report.field_counts
    assert report.mismatches and set(report.mismatches[0]) == {"sequence", "field", "logged", "replayed"}
    assert "differ" in report.describe()
    assert any("manifest differs" in n for n in report.notes)


def test_compare_results_rules():
    a = [{"sequence": i, "stamp_ns": i, "p_new": 0.1 * i, "loop": False, "timings_ms": {"x": i}} for i in range(4)]
    b = [dict(d, timings_ms={"x": 99}, p_new=d["p_new"] * (1 + 1e-9)) for d in a]
    r = compare_results(a, b)
    assert r.ok and r.compared == 4  # timings ignored, float tolerance
    b[2]["loop"] = True
    r = compare_results(a, b)
    assert not r.ok and r.field_counts == {"loop": 1} and r.mismatches[0]["sequence"] == 2
    r = compare_results(a, b[:3] + [], fields=("stamp_ns",))
    assert r.only_in_log == 1 and not r.ok
    r = compare_results(a, a[:3], truncated=True)
    assert r.ok and r.tail_ignored == 1
    assert {"timings_ms", "latency_ms", "frame_seq"} <= set(NONDETERMINISTIC_FIELDS)
    # a field only one side has is a difference (format drift), an ignored one is not
    c = [dict(d, n_places=1, latency_ms=5.0, frame_seq=7) for d in a]
    r = compare_results(a, c)
    assert r.field_counts == {"n_places": 4}


def test_replay_of_a_truncated_log(live_log, tmp_path):
    data = live_log.read_bytes()
    # rewrite with small chunks so that a cut keeps several complete chunks
    small = tmp_path / "small.mcap"
    src = McapLogReader(live_log)
    with McapLogWriter(small, McapLogConfig(chunk_size=2048), manifest=FakeDetector().manifest) as w:
        frames = list(src.frames())
        for f, res in zip(frames, src.results):
            w.write_image(f.payload, f.encoding, f.stamp_ns, sequence=f.sequence)
            w.write_result(res)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(small.read_bytes()[: int(small.stat().st_size * 0.6)])
    summary = replay(FakeDetector(), cut, check=True)
    assert summary.status.truncated and 0 < summary.frames_processed < 16
    assert summary.check.ok, summary.check.describe()
    assert any("truncated" in n for n in summary.check.notes)
    assert len(data) > 0


def test_sparse_image_log_is_flagged_incomplete(tmp_path):
    path = tmp_path / "sparse.mcap"
    det = FakeDetector()
    images = sample_images(6, size=(64, 48))
    from aefabmap_runtime.adapters.frames import encode_frame

    with McapLogWriter(path, McapLogConfig(image_every=2)) as w:
        for i, img in enumerate(images):
            payload, enc = encode_frame(img, "png")
            res = det.process(img, i).to_dict()
            w.write_image(payload, enc, i, sequence=i)
            w.write_result(res)
    summary = replay(FakeDetector(), path, check=True)
    assert summary.frames_processed == 3
    assert not summary.check.complete and not summary.check.ok
    assert any("image_every" in n for n in summary.check.notes)


def test_ros2_bag_replays(tmp_path):
    images = sample_images(10, size=(96, 72))
    bag = tmp_path / "ros2.mcap"
    stamps = write_ros2_bag(bag, images)
    if rosbags_available():  # without rosbags a ROS 2 .mcap goes to the MCAP reader (first topic)
        with pytest.raises(LogError, match="several image topics.*/cam/compressed, /cam/raw"):
            replay(FakeDetector(), bag)  # two image topics and none chosen: listed, not guessed
    seen = []
    summary = replay(FakeDetector(), bag, image_topic="/cam/compressed", on_result=seen.append)
    assert summary.frames_processed == 10 and summary.status.image_topic == "/cam/compressed"
    assert [d["stamp_ns"] for d in seen] == stamps
    raw = replay(FakeDetector(), bag, image_topic="/cam/raw", out_path=tmp_path / "from_raw.mcap")
    assert raw.frames_processed == 10 and sum(raw.bad.values()) == 0
    r = McapLogReader(tmp_path / "from_raw.mcap")
    out_frames = list(r.frames())
    assert len(out_frames) == 10 and out_frames[0].encoding == "image/png"
    assert all(np.array_equal(f.decode(), img) for f, img in zip(out_frames, images))
    # no results in a bag: --check has nothing to compare
    checked = replay(FakeDetector(), bag, check=True, image_topic="/cam/raw")
    assert not checked.check.ok and any("no /lcd/result" in n for n in checked.check.notes)


def test_cli_replay_main(live_log, tmp_path, monkeypatch, capsys):
    import aefabmap_runtime.adapters.bundle_reader as bundle_reader_mod
    from aefabmap.cli import replay as cli_replay

    monkeypatch.setattr(bundle_reader_mod, "load_detector", lambda *a, **k: FakeDetector())
    args = cli_args("replay", live_log, "--model", "fake", "--out", tmp_path / "o.mcap", "--check")
    assert cli_replay.main(args) == 0
    doc = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert doc["check"]["ok"] and doc["frames_processed"] == 16
    monkeypatch.setattr(bundle_reader_mod, "load_detector", lambda *a, **k: FakeDetector(threshold=0.5))
    assert cli_replay.main(args) == 1
    args = cli_args("replay", tmp_path / "missing.mcap", "--model", "fake")
    assert cli_replay.main(args) == 6  # LogError exit code


def _live_run(detector, images, encoding: str, log_path, *, rate_hz: float, **options):
    """A live node logging to log_path while `images` are published to it: (its result docs,
    up to the last frame's, and its summary)."""
    listen, connect = session_pair()
    with NodeThread(detector=detector, session_config=listen, key=KEY, mcap_path=log_path, stats_period_s=1.0,
                    **options) as node:
        with open_session(connect) as s:
            results = JsonCollector(s, "robot/camera/lcd")
            publish_frames(connect, KEY, array_source(images, encoding), rate_hz=rate_hz, wait_for_subscriber_s=10)
            docs = results.wait_for(lambda d: d["sequence"] == len(images) - 1, timeout_s=60)
            results.close()
        return docs, node.finish()


def test_real_detector_live_then_replay_check(tmp_path):
    """The lead's LoopClosureDetector on a small synthetic bundle: live log -> replay --check OK."""
    from aefabmap_runtime.adapters.bundle_reader import load_detector
    from aefabmap_runtime.core.detector import DetectorConfig
    from tests.conftest import make_synthetic_bundle

    bundle = make_synthetic_bundle(tmp_path / "bundle")
    config = DetectorConfig(exclude=2)
    log_path = tmp_path / "real.mcap"
    docs, summary = _live_run(load_detector(bundle, config), sample_images(20, size=(160, 120)), "jpeg", log_path,
                              rate_hz=100, queue_size=32)
    assert summary.frames_processed == 20 and summary.bad_total == 0
    assert any(d["inserted_place"] is not None for d in docs)
    replayed = replay(load_detector(bundle, config), log_path, check=True)
    assert replayed.check.ok, replayed.check.describe()
    assert replayed.check.compared == 20


def _schemas_in_log(path) -> dict[str, dict]:
    """topic -> the JSON schema the log itself carries for that channel."""
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    return {c.topic: json.loads(summary.schemas[c.schema_id].data) for c in summary.channels.values()
            if summary.schemas[c.schema_id].encoding == "jsonschema"}


def _raw_json_messages(path) -> dict[str, list[dict]]:
    from mcap.reader import make_reader

    out: dict[str, list[dict]] = {}
    with open(path, "rb") as f:
        for _, channel, message in make_reader(f).iter_messages():
            if channel.message_encoding == "json":
                out.setdefault(channel.topic, []).append(json.loads(message.data))
    return out


def _conforms(doc: dict, schema: dict) -> None:
    from aefabmap_runtime.core.records.json_schema import validate

    assert validate(doc, schema) is None, (validate(doc, schema), doc)
    assert set(doc) <= set(schema["properties"]), set(doc) - set(schema["properties"])  # no undeclared key


def test_real_run_messages_conform_to_the_schemas_written_in_the_log(tmp_path):
    """Zenoh results/stats and MCAP records of a real run (real detector, loopback Zenoh),
    the first stats message (nulls, before any frame) included, then those of its replay."""
    from aefabmap_runtime.adapters.bundle_reader import load_detector
    from aefabmap_runtime.core.detector import DetectorConfig
    from aefabmap_runtime.core.records.messages import RunSummary
    from tests.conftest import make_synthetic_bundle

    bundle = make_synthetic_bundle(tmp_path / "bundle")
    config = DetectorConfig(exclude=2)
    listen, connect = session_pair()
    log_path = tmp_path / "real.mcap"
    with NodeThread(detector=load_detector(bundle, config), session_config=listen, key=KEY,
                    mcap_path=log_path, queue_size=32, stats_period_s=0.2) as node:
        with open_session(connect) as s:
            results = JsonCollector(s, "robot/camera/lcd")
            stats = JsonCollector(s, "robot/camera/lcd/stats")
            first_stats = stats.wait_for(lambda d: True, timeout_s=20)[0]
            publish_frames(connect, KEY, array_source(sample_images(12, size=(160, 120)), "jpeg"), rate_hz=100,
                           wait_for_subscriber_s=10)
            docs = results.wait_for(lambda d: d["sequence"] == 11, timeout_s=60)
            stat_docs = stats.wait_for(lambda d: d["frames_processed"] == 12, timeout_s=20)
            results.close()
            stats.close()
        summary = node.finish()
    assert first_stats["frames_processed"] == 0 and first_stats["latency_ms"] == {"p50": None, "p95": None}
    schemas = _schemas_in_log(log_path)
    assert set(schemas) == {"/lcd/result", "/lcd/stats"}
    logged = _raw_json_messages(log_path)
    assert len(logged["/lcd/result"]) == 12 and logged["/lcd/stats"]
    for doc in docs + logged["/lcd/result"]:
        _conforms(doc, schemas["/lcd/result"])
        assert doc["score_kind"] == "probability" and {"frame_seq", "latency_ms", "age_ms"} <= set(doc)
    for doc in [first_stats, *stat_docs, *logged["/lcd/stats"]]:
        _conforms(doc, schemas["/lcd/stats"])
    _conforms(summary.to_dict(), RunSummary.json_schema())
    # the replay's own log conforms to its schemas too (no transport fields, a final stats)
    out = tmp_path / "re.mcap"
    rep = replay(load_detector(bundle, config), log_path, out_path=out, check=True)
    assert rep.check.ok, rep.check.describe()
    re_logged, re_schemas = _raw_json_messages(out), _schemas_in_log(out)
    assert len(re_logged["/lcd/result"]) == 12 and len(re_logged["/lcd/stats"]) == 1
    for topic, messages in re_logged.items():
        for doc in messages:
            _conforms(doc, re_schemas[topic])


def test_replay_check_of_an_older_format_log_skips_the_fields_it_cannot_hold(live_log, tmp_path, monkeypatch):
    """A format-1 log (no score_kind; written as the old code did) still checks OK with the
    real detector, whose results now carry score_kind; the report says what was not compared."""
    from aefabmap_runtime.adapters import mcap_log
    from aefabmap_runtime.adapters.bundle_reader import load_detector
    from aefabmap_runtime.core.detector import DetectorConfig
    from tests.conftest import make_synthetic_bundle

    bundle = make_synthetic_bundle(tmp_path / "bundle")
    config = DetectorConfig(exclude=2)
    det = load_detector(bundle, config)
    src = McapLogReader(live_log)
    frames = list(src.frames())
    old = tmp_path / "v1.mcap"
    monkeypatch.setattr(mcap_log, "LOG_FORMAT_VERSION", "1")
    with McapLogWriter(old, manifest=det.manifest) as w:
        for f in frames:
            res = det.process(f.decode(), f.stamp_ns).to_dict()
            for newer in ("score_kind", "nfa", "geometry_reason", "candidates"):  # fields added after format 1
                del res[newer]
            w.write_image(f.payload, f.encoding, f.stamp_ns, sequence=res["sequence"])
            w.write_result(res)
    monkeypatch.undo()
    summary = replay(load_detector(bundle, config), old, check=True)
    assert summary.status.format_version == "1"
    assert summary.check.ok and summary.check.compared == 16, summary.check.describe()
    assert any("not compared:" in n and "score_kind" in n and "nfa" in n for n in summary.check.notes)
    again = replay(load_detector(bundle, config), live_log, check=True)  # a current log: nothing skipped
    assert not any("not compared" in n for n in again.check.notes)


def _read(path) -> tuple[McapLogReader, list]:
    """A reader of the log at path read through (metadata and results with it), and its frames."""
    reader = McapLogReader(path)
    return reader, list(reader.frames())


def _copy_log(src, dst) -> None:
    """Rewrite the images and results of log src into a new log dst (this build's writer)."""
    reader, frames = _read(src)
    with McapLogWriter(dst, manifest=reader.manifest) as w:
        for f, res in zip(frames, reader.results, strict=True):
            w.write_image(f.payload, f.encoding, f.stamp_ns, sequence=res.sequence)
            w.write_result(res)


def test_logs_record_the_extraction_version_and_a_check_says_when_it_differs(live_log, tmp_path, monkeypatch):
    """A log names the feature extraction of the build that wrote it (features.EXTRACTION_VERSION):
    replayed by a build that extracts otherwise, the check says why frames may differ."""
    from aefabmap_runtime.adapters import mcap_log
    from aefabmap_runtime.core.features.features import EXTRACTION_VERSION

    assert _read(live_log)[0].extraction_version == EXTRACTION_VERSION
    same = replay(FakeDetector(), live_log, check=True).check
    assert same.ok and not any("extraction" in n for n in same.notes)
    older = tmp_path / "older.mcap"
    monkeypatch.setattr(mcap_log, "EXTRACTION_VERSION", EXTRACTION_VERSION - 1)
    _copy_log(live_log, older)
    monkeypatch.undo()
    assert _read(older)[0].extraction_version == EXTRACTION_VERSION - 1
    report = replay(FakeDetector(), older, check=True).check
    assert report.ok  # this detector does not extract features: the note says what could differ
    assert any(f"extraction version {EXTRACTION_VERSION - 1}, this build {EXTRACTION_VERSION}" in n
               for n in report.notes)


def test_a_set_of_logs_has_an_extraction_version_only_when_its_files_agree(live_log, tmp_path, monkeypatch):
    from aefabmap_runtime.adapters import mcap_log
    from aefabmap_runtime.adapters.log_set import LogSetReader
    from aefabmap_runtime.core.features.features import EXTRACTION_VERSION

    same, other = tmp_path / "same.mcap", tmp_path / "other.mcap"
    _copy_log(live_log, same)
    monkeypatch.setattr(mcap_log, "EXTRACTION_VERSION", EXTRACTION_VERSION + 1)
    _copy_log(live_log, other)
    monkeypatch.undo()
    for files, expected in (([live_log, same], EXTRACTION_VERSION), ([live_log, other], None)):
        reader = LogSetReader(files)
        list(reader.frames())
        assert reader.extraction_version == expected


@pytest.mark.parametrize("value", ["", "0", "-1", "x", "\u00b2", "1234567", "2.0", " 2"])
def test_a_log_without_a_readable_extraction_version_is_named_only_when_results_differ(live_log, tmp_path,
                                                                                        monkeypatch, value):
    """Logs written before the version was recorded (or hostile values) read as None: a check
    that finds differences says the log does not record it; one that finds none says nothing."""
    from aefabmap_runtime.adapters import mcap_log

    log = tmp_path / "unrecorded.mcap"
    monkeypatch.setattr(mcap_log, "EXTRACTION_VERSION", value)
    _copy_log(live_log, log)
    monkeypatch.undo()
    assert _read(log)[0].extraction_version is None
    assert not any("extraction" in n for n in replay(FakeDetector(), log, check=True).check.notes)
    differing = replay(FakeDetector(threshold=0.5), log, check=True).check
    assert differing.mismatched > 0
    assert any("does not record its feature extraction version" in n for n in differing.notes)


class _FakeClock:
    """A monotonic clock and a stop event whose waits advance it (no real time passes)."""

    def __init__(self) -> None:
        self.now, self.waits, self.stopped = 100.0, [], False

    def __call__(self) -> float:
        return self.now

    def wait(self, timeout_s: float) -> bool:
        self.waits.append(round(timeout_s, 6))
        self.now += timeout_s
        return self.stopped

    def is_set(self) -> bool:
        return self.stopped


def test_pacer_waits_the_recorded_gaps_without_adding_processing_time():
    from aefabmap_runtime.adapters.replay import Pacer, PlaybackConfig

    clock = _FakeClock()
    pacer = Pacer(PlaybackConfig(rate=1.0, max_gap_s=3.0), stop=clock, clock=clock)
    s = 10**9  # ns
    for stamp in (0, s // 2, s):  # frames 0.5 s apart, 0.2 s of processing each
        assert pacer.wait(stamp)
        clock.now += 0.2
    assert clock.waits == [0.3, 0.3]  # the gap minus the processing, not the gap on top of it
    assert pacer.wait(101 * s) and clock.waits[-1] == 2.8  # a 100 s pause in the log: capped at 3 s
    n = len(clock.waits)
    assert pacer.wait(100 * s) and len(clock.waits) == n  # a stamp going back (next run): no wait
    clock.now += 60.0  # a long stall: re-anchored, no burst of 60 s worth of frames
    for stamp in (100 * s + s // 2, 101 * s, 102 * s, 103 * s, 104 * s):
        assert pacer.wait(stamp)
    assert clock.waits[n:] == [0.5]  # at most max_gap_s (3 s) of frames at once, then paced again
    double = Pacer(PlaybackConfig(rate=2.0), stop=clock, clock=clock)
    assert double.wait(0) and double.wait(s) and clock.waits[-1] == 0.5
    clock.stopped = True
    assert not double.wait(2 * s)  # stopped while waiting
    assert not Pacer(PlaybackConfig(rate=0.0), stop=clock, clock=clock).wait(0)  # stopped before a frame


def test_playback_config_is_validated():
    from aefabmap_runtime.errors import ConfigError
    from aefabmap_runtime.adapters.replay import PlaybackConfig

    for bad in ({"rate": -1.0}, {"rate": float("nan")}, {"rate": float("inf")}, {"max_gap_s": 0},
                {"wait_viewer_s": 0}, {"wait_viewer_s": float("inf")}):
        with pytest.raises(ConfigError):
            PlaybackConfig(**bad)


def _paced_log(path, n: int, gap_s: float):
    import cv2

    with McapLogWriter(path) as log:
        for i, img in enumerate(sample_images(n, size=(96, 72))):
            _ok, png = cv2.imencode(".png", img)
            log.write_image(png.tobytes(), "image/png", 1_700_000_000_000_000_000 + round(i * gap_s * 1e9), sequence=i)
    return path


def test_replay_rate_keeps_the_recorded_pace_and_rate_0_does_not_wait(tmp_path):
    """Rough timing (slow CI machines): lower bounds from the recorded gaps, upper bounds generous."""
    import threading

    from aefabmap_runtime.adapters.replay import PlaybackConfig

    src = _paced_log(tmp_path / "paced.mcap", 6, gap_s=0.3)  # 1.5 s recorded
    fast_docs, again_docs = [], []
    fast = replay(FakeDetector(), src, on_result=fast_docs.append)
    paced = replay(FakeDetector(), src, playback=PlaybackConfig(rate=1.0))
    double = replay(FakeDetector(), src, playback=PlaybackConfig(rate=2.0))
    assert 1.4 <= paced.duration_s < 10 and 0.7 <= double.duration_s < paced.duration_s
    # Processing time is not added to the gaps: 0.25 s per frame inside 0.3 s gaps.
    slow = replay(FakeDetector(delay_s=0.25), src, playback=PlaybackConfig(rate=1.0))
    assert slow.duration_s < 1.5 + 6 * 0.25 - 0.3  # blind sleeps would take 1.5 + 6 * 0.25
    waits = []

    class _Watch(threading.Event):
        def wait(self, timeout=None):
            waits.append(timeout)
            return super().wait(timeout)

    again = replay(FakeDetector(), src, playback=PlaybackConfig(rate=0.0), stop=_Watch(), on_result=again_docs.append)
    assert waits == [] and fast.frames_processed == paced.frames_processed == again.frames_processed == 6
    assert compare_results(fast_docs, again_docs).ok  # --rate 0: the default replay, unchanged
    assert not fast.stopped and fast.to_dict()["stopped"] is False


def test_a_stop_ends_a_paced_replay_between_frames(tmp_path):
    import threading
    import time

    from aefabmap_runtime.adapters.replay import PlaybackConfig

    src = _paced_log(tmp_path / "pauses.mcap", 5, gap_s=100.0)  # long pauses: capped, then stopped
    stop = threading.Event()
    seen = []

    def on_result(doc: dict) -> None:
        seen.append(doc["sequence"])
        if len(seen) == 2:
            threading.Timer(0.2, stop.set).start()  # Ctrl-C during the (capped) wait for frame 2

    t0 = time.monotonic()
    summary = replay(FakeDetector(), src, playback=PlaybackConfig(rate=1.0, max_gap_s=3.0), on_result=on_result,
                     stop=stop)
    assert summary.stopped and summary.frames_processed == 2 and seen == [0, 1]
    assert time.monotonic() - t0 < 3.0 + 2.5  # one capped gap, then the stop within its wait


def test_a_node_and_a_replay_with_two_workers_give_one_threads_results(tmp_path):
    """`run --workers 2` on a live stream and `replay --workers 2` of its log: every frame decided in
    order, and the replay's --check (all fields but the timings) passes against the live results,
    as does a one-thread replay."""
    from aefabmap.cli.demo import default_bundle
    from aefabmap_runtime.adapters.bundle_reader import load_detector
    from aefabmap_runtime.core.detector import DetectorConfig
    from aefabmap_runtime.tools.synthetic_route import generate_loop_sequence

    config = DetectorConfig(exclude=3)
    log_path = tmp_path / "two.mcap"
    images, _ = generate_loop_sequence(24, seed=5, size=(320, 240))
    docs, summary = _live_run(load_detector(default_bundle(), config), images, "png", log_path, rate_hz=50,
                              queue_size=64, workers=2)
    assert summary.frames_processed == 24 and summary.bad_total == 0
    assert [d["sequence"] for d in docs] == list(range(24)) and any(d["verified"] for d in docs)
    for workers in (2, 1):
        replayed = replay(load_detector(default_bundle(), config), log_path, check=True, workers=workers)
        assert replayed.check.ok and replayed.check.compared == 24, replayed.check.describe()


def _replay_process(log, timeout_s: float = 30):
    """`aefabmap replay LOG --model <shipped bundle>` as a child process (a hang fails the test)."""
    import subprocess

    from aefabmap.cli.options import default_bundle

    from .stream_fakes import CLI

    return subprocess.run(CLI + ["replay", str(log), "--model", str(default_bundle())], capture_output=True,
                          text=True, timeout=timeout_s, check=False)


@pytest.mark.parametrize("name", ["fifo.mcap", "fifo.db3"])
def test_replay_of_a_fifo_says_it_is_not_a_regular_file(tmp_path, name):
    """The attack: a FIFO was reported as "does not exist" (an .mcap) or opened (a .db3)."""
    import os

    fifo = tmp_path / name
    os.mkfifo(fifo)
    done = _replay_process(fifo)
    assert done.returncode == LogError.exit_code, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and f"{fifo} is not a regular file" in lines[0], done.stderr


@pytest.mark.parametrize("rest", [b"x", b"\x01\x04\x00\x00\x00\x00\x00\x00\x00abcd", b"\x01" + b"\xff" * 8])
def test_a_broken_file_with_the_mcap_magic_is_a_damaged_mcap_log(tmp_path, rest):
    """The attack: a file that starts with the MCAP magic and then breaks was reported as a ROS bag
    that cannot be read, with the reader library's exception name."""
    broken = tmp_path / "broken.mcap"
    broken.write_bytes(b"\x89MCAP0\r\n" + rest)
    done = _replay_process(broken)
    assert done.returncode == LogError.exit_code, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and f"{broken} is a damaged MCAP log" in lines[0], done.stderr
    assert "ROS bag" not in lines[0] and "Traceback" not in done.stderr
