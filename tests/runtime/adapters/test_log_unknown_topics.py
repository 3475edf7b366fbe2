"""Topics of a log that the reader does not know are listed, with their message counts
(runtime/aefabmap_runtime/adapters/mcap_log.py ReadStatus.unknown_topics), not skipped silently."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
from mcap.reader import make_reader
from mcap.writer import Writer

from aefabmap.cli.options import default_bundle
from aefabmap_runtime.adapters.foxglove_view import ANNOTATIONS_TOPIC
from aefabmap_runtime.adapters.frames import encode_frame
from aefabmap_runtime.adapters.log_set import open_log_reader
from aefabmap_runtime.adapters.mcap_log import McapLogReader, McapLogWriter
from aefabmap_runtime.core.records.messages import StatsMessage

from .stream_fakes import make_result, sample_images

pytestmark = pytest.mark.timeout(120)
EXTRA = "/robot/odometry"


def _own_log(path, n: int = 6) -> None:
    """A log as `run` writes it: images, results, stats and a live-view topic (known, not replayed)."""
    with McapLogWriter(path, manifest={"format_version": 1}) as w:
        for i, img in enumerate(sample_images(n, size=(320, 240))):
            payload, enc = encode_frame(img, "png")
            w.write_image(payload, enc, 1_000 + i, sequence=i)
            w.write_result(make_result(i, 1_000 + i))
            w.write_view(ANNOTATIONS_TOPIC, b"", 1_000 + i, sequence=i)
        w.write_stats(StatsMessage(stamp_ns=1, uptime_s=0.0, frames_received=n, frames_processed=n, dropped=0,
                                   bad={}, loops=0))


def _with_extra_topic(src, dst, messages: int) -> None:
    """dst: every record of src, plus `messages` JSON messages on EXTRA and a channel with none on /silent."""
    with open(src, "rb") as f, open(dst, "wb") as g:
        reader = make_reader(f)
        w = Writer(g)
        w.start(profile=reader.get_header().profile, library="test")
        for m in reader.iter_metadata():
            w.add_metadata(m.name, m.metadata)
        schemas, channels = {}, {}
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            if schema.id not in schemas:
                schemas[schema.id] = w.register_schema(schema.name, schema.encoding, schema.data)
            if channel.id not in channels:
                channels[channel.id] = w.register_channel(channel.topic, channel.message_encoding,
                                                          schemas[schema.id], channel.metadata)
            w.add_message(channels[channel.id], message.log_time, message.data, message.publish_time,
                          message.sequence)
        odometry = w.register_schema("robot.Odometry", "jsonschema", b"{}")
        extra = w.register_channel(EXTRA, "json", odometry)
        w.register_channel("/silent", "json", odometry)
        for i in range(messages):
            w.add_message(extra, 2_000 + i, json.dumps({"x": i}).encode(), 2_000 + i, i)
        w.finish()


def test_the_reader_lists_unknown_topics_and_not_its_own(tmp_path):
    _own_log(tmp_path / "own.mcap")
    plain = McapLogReader(tmp_path / "own.mcap")
    assert len(list(plain.frames())) == 6
    assert plain.status.unknown_topics == {}  # the live view's topic is aefabmap's own

    _with_extra_topic(tmp_path / "own.mcap", tmp_path / "extra.mcap", messages=4)
    reader = McapLogReader(tmp_path / "extra.mcap")
    assert len(list(reader.frames())) == 6 and len(reader.results) == 6
    assert reader.status.unknown_topics == {EXTRA: 4, "/silent": 0}
    assert f"{EXTRA} (4 messages)" in reader.status.describe()
    assert reader.status.to_dict()["unknown_topics"] == {EXTRA: 4, "/silent": 0}


def test_a_log_set_adds_up_the_unknown_topics_of_its_files(tmp_path):
    logs = tmp_path / "logs"
    logs.mkdir()
    _own_log(tmp_path / "own.mcap")
    _with_extra_topic(tmp_path / "own.mcap", logs / "run-0001.mcap", messages=2)
    _with_extra_topic(tmp_path / "own.mcap", logs / "run-0002.mcap", messages=3)
    reader = open_log_reader([str(logs)])
    list(reader.frames())
    assert reader.status.unknown_topics == {EXTRA: 5, "/silent": 0}


def test_replay_lists_the_unknown_topics_in_its_summary(tmp_path):
    _own_log(tmp_path / "own.mcap")
    _with_extra_topic(tmp_path / "own.mcap", tmp_path / "extra.mcap", messages=4)
    out = subprocess.run([sys.executable, "-m", "aefabmap.cli.main", "replay", str(tmp_path / "extra.mcap"),
                          "--model", str(default_bundle())], capture_output=True, text=True, timeout=100)
    assert out.returncode == 0, out.stderr
    summary = json.loads(out.stdout.strip().splitlines()[-1])
    assert summary["frames_processed"] == 6 and summary["status"]["unknown_topics"] == {EXTRA: 4, "/silent": 0}
    assert f"{EXTRA} (4 messages)" in out.stderr and "Traceback" not in out.stderr


def test_a_log_of_many_unknown_topics_is_described_in_one_short_line(tmp_path):
    path = tmp_path / "many.mcap"
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        schema = w.register_schema("x.Y", "jsonschema", b"{}")
        for i in range(25):
            w.add_message(w.register_channel(f"/t{i:02d}/" + "x" * 500, "json", schema), i, b"{}", i, 0)
        w.finish()
    reader = McapLogReader(path)
    assert list(reader.frames()) == [] and len(reader.status.unknown_topics) == 25
    line = reader.status.describe()
    assert "\n" not in line and line.endswith(" and 15 more") and len(line) < 2000
