"""MCAP writer/reader (runtime/aefabmap_runtime/adapters/mcap_log.py): layout, crash safety, ROS 2 bags."""

from __future__ import annotations

import json
import os
import select
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory as ProtobufDecoderFactory

from aefabmap_runtime.errors import LogError
from aefabmap_runtime.adapters.frames import encode_frame
from aefabmap_runtime.adapters.mcap_log import (
    IMAGE_TOPIC,
    MANIFEST_METADATA,
    RESULT_TOPIC,
    RUN_CONFIG_METADATA,
    STATS_TOPIC,
    McapLogConfig,
    McapLogReader,
    McapLogWriter,
    read_log_metadata,
)
from aefabmap_runtime.core.records.messages import StatsMessage

from .stream_fakes import make_result, sample_images, write_ros2_bag

pytestmark = pytest.mark.timeout(60)


def _write_log(path, images, *, config=None, manifest=None):
    with McapLogWriter(path, config, manifest=manifest or {"format_version": 1}, run_config={"key": "a/b"}) as w:
        for i, img in enumerate(images):
            fmt = ("jpeg", "png", "mono8")[i % 3]
            payload, enc = encode_frame(img, fmt)
            w.write_image(payload, enc, 1_000 + i, sequence=i)
            w.write_result(make_result(i, 1_000 + i, loop=i % 2 == 0))
        w.write_stats(StatsMessage(stamp_ns=1, uptime_s=0.0, frames_received=len(images),
                                   frames_processed=len(images), dropped=0, bad={}, loops=0))
    return w


def test_roundtrip_layout_schemas_and_metadata(tmp_path):
    images = sample_images(6, size=(64, 48))
    path = tmp_path / "run.mcap"
    w = _write_log(path, images, manifest={"vocabulary_size": 1000, "files": {"a": "sha"}})
    assert w.images_written == 6 and w.messages_written == 13
    # standard reader: summary present, channels and schemas as documented
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[ProtobufDecoderFactory()])
        summary = reader.get_summary()
        topics = {c.topic: c for c in summary.channels.values()}
        assert set(topics) == {IMAGE_TOPIC, RESULT_TOPIC, STATS_TOPIC}
        schema = summary.schemas[topics[IMAGE_TOPIC].schema_id]
        assert (schema.name, schema.encoding) == ("foxglove.CompressedImage", "protobuf")
        for t in (RESULT_TOPIC, STATS_TOPIC):
            assert topics[t].message_encoding == "json"
            assert summary.schemas[topics[t].schema_id].encoding == "jsonschema"
            json.loads(summary.schemas[topics[t].schema_id].data)
        decoded = [m for _, _, _, m in reader.iter_decoded_messages(topics=[IMAGE_TOPIC])]
        assert [m.format for m in decoded] == ["jpeg", "png", "png"] * 2
        assert decoded[0].timestamp.ToNanoseconds() == 1000
    # our reader
    r = McapLogReader(path)
    frames = list(r.frames())
    assert len(frames) == 6 and [f.stamp_ns for f in frames] == list(range(1000, 1006))
    assert [f.sequence for f in frames] == list(range(6))
    assert np.array_equal(frames[1].decode(), images[1])  # png lossless
    assert np.array_equal(frames[2].decode(), images[2])  # raw stored as gray png
    assert [d.sequence for d in r.results] == list(range(6))
    assert [s.frames_processed for s in r.stats] == [6] and r.status.invalid_messages == 0
    assert r.manifest == {"vocabulary_size": 1000, "files": {"a": "sha"}}
    assert r.metadata[RUN_CONFIG_METADATA] == {"key": "a/b"}
    assert not r.status.truncated and r.status.messages_read == 13
    assert read_log_metadata(path)[MANIFEST_METADATA]["vocabulary_size"] == 1000
    with pytest.raises(LogError):
        list(r.frames())  # single pass


def test_image_every_n(tmp_path):
    path = tmp_path / "sparse.mcap"
    images = sample_images(7, size=(32, 32))
    _write_log(path, images, config=McapLogConfig(image_every=3))
    r = McapLogReader(path)
    assert [f.sequence for f in r.frames()] == [0, 3, 6]
    assert len(r.results) == 7


def test_unwritable_path_is_log_error_naming_path(tmp_path):
    bad = tmp_path / "no" / "such" / "dir" / "run.mcap"
    with pytest.raises(LogError, match=str(bad)):
        McapLogWriter(bad)
    with pytest.raises(LogError, match=str(tmp_path)):
        McapLogWriter(tmp_path)  # a directory


def test_bad_config_and_bad_input_files(tmp_path):
    from aefabmap_runtime.errors import ConfigError

    with pytest.raises(ConfigError):
        McapLogConfig(compression="brotli")
    with pytest.raises(ConfigError):
        McapLogConfig(chunk_size=10)
    with pytest.raises(LogError, match="does not exist"):
        McapLogReader(tmp_path / "missing.mcap")
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"this is not an mcap file")
    with pytest.raises(LogError, match="not an MCAP"):
        McapLogReader(junk)


def test_truncated_files_read_up_to_last_complete_chunk(tmp_path):
    path = tmp_path / "full.mcap"
    images = sample_images(30, size=(64, 48))
    _write_log(path, images, config=McapLogConfig(chunk_size=4096))
    data = path.read_bytes()
    full = McapLogReader(path)
    n_full = len(list(full.frames()))
    previous = -1
    for frac in (0.2, 0.5, 0.8, 0.97):
        cut = tmp_path / f"cut{frac}.mcap"
        cut.write_bytes(data[: int(len(data) * frac)])
        r = McapLogReader(cut)
        frames = list(r.frames())  # must not raise
        assert r.status.truncated and "truncated" in r.status.describe()
        assert 0 <= len(frames) <= n_full
        assert len(frames) >= previous
        previous = len(frames)
        assert [d.sequence for d in r.results] == list(range(len(r.results)))
        assert r.manifest == {"format_version": 1}  # metadata written at open survives
    assert previous > 0


_KILLED_WRITER = textwrap.dedent(
    """
    import sys
    from aefabmap_runtime.adapters.frames import encode_frame
    from aefabmap_runtime.adapters.mcap_log import McapLogConfig, McapLogWriter
    import numpy as np
    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, size=(48, 64), dtype=np.uint8)
    payload, enc = encode_frame(img, "png")
    w = McapLogWriter(sys.argv[1], McapLogConfig(chunk_size=8192, flush_interval_s=0.05), manifest={"m": 1})
    i = 0
    while True:
        w.write_image(payload, enc, i, sequence=i)
        w.write_result({"sequence": i, "stamp_ns": i})
        i += 1
        if i % 25 == 0:
            print(i, flush=True)
    """
)


def test_sigkilled_writer_leaves_a_readable_log(tmp_path):
    path = tmp_path / "killed.mcap"
    proc = subprocess.Popen([sys.executable, "-c", _KILLED_WRITER, str(path)], stdout=subprocess.PIPE, text=True)
    try:
        written = 0
        deadline = time.monotonic() + 30
        while written < 300:
            ready, _, _ = select.select([proc.stdout], [], [], max(0.0, deadline - time.monotonic()))
            assert ready, "writer subprocess produced nothing"
            line = proc.stdout.readline()
            assert line, f"writer exited early with {proc.poll()}"
            written = int(line)
        os.kill(proc.pid, signal.SIGKILL)
        assert proc.wait(10) == -signal.SIGKILL
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
    r = McapLogReader(path)
    frames = list(r.frames())
    assert r.status.truncated
    assert r.manifest == {"m": 1}
    # everything up to the last complete chunk: all but the last chunk's worth of frames
    assert len(frames) >= written - 100, (len(frames), written)
    assert r.status.messages_read >= 2 * len(frames) - 1
    assert [f.sequence for f in frames] == list(range(len(frames)))
    assert np.array_equal(frames[-1].decode(), frames[0].decode())


def test_ros2_bag_compressed_and_raw_images(tmp_path):
    images = sample_images(5, size=(64, 48))
    path = tmp_path / "bag.mcap"
    stamps = write_ros2_bag(path, images)
    r = McapLogReader(path)  # default: first image topic found
    frames = list(r.frames())
    assert r.status.image_topic == "/cam/compressed" and r.status.ignored_image_topics == ["/cam/raw"]
    assert [f.stamp_ns for f in frames] == stamps
    assert all(f.encoding == "image/jpeg" for f in frames)
    assert np.abs(frames[0].decode().astype(int) - images[0]).mean() < 6
    raw = McapLogReader(path, image_topic="/cam/raw")
    rframes = list(raw.frames())
    assert len(rframes) == 5 and rframes[0].encoding == "mono8;64x48"
    assert all(np.array_equal(f.decode(), img) for f, img in zip(rframes, images))
    assert r.results == [] and r.manifest is None


def _raw_log(path, *, version: str | None, results: list[dict], result_topic: str = "/lcd/result") -> None:
    """A log written by hand: metadata aefabmap.log (when version), one results channel."""
    from mcap.writer import Writer

    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        if version is not None:
            w.add_metadata("aefabmap.log", {"format_version": version})
        sid = w.register_schema(name="aefabmap.LcdResult", encoding="jsonschema", data=b"{}")
        cid = w.register_channel(topic=result_topic, message_encoding="json", schema_id=sid)
        for i, doc in enumerate(results):
            w.add_message(channel_id=cid, log_time=i, publish_time=i, sequence=i, data=json.dumps(doc).encode())
        w.finish()


def test_log_format_version_newer_major_is_refused_older_is_read(tmp_path):
    old_doc = {k: v for k, v in make_result(0, 5).to_dict().items() if k != "score_kind"}
    old = tmp_path / "v1.mcap"
    _raw_log(old, version="1", results=[old_doc], result_topic="/old/name")
    r = McapLogReader(old)
    list(r.frames())
    assert r.format_version == (1, 0) and r.status.format_version == "1"
    assert [x.stamp_ns for x in r.results] == [5] and r.results[0].score_kind is None
    new = tmp_path / "v2.mcap"
    _raw_log(new, version="2.0", results=[old_doc])
    with pytest.raises(LogError, match=r"format 2\.0 is newer than this aefabmap reads") as err:
        list(McapLogReader(new).frames())
    assert "\n" not in str(err.value) and str(new) in str(err.value)
    with pytest.raises(LogError, match="newer"):
        read_log_metadata(new)
    junk = tmp_path / "vjunk.mcap"
    _raw_log(junk, version="one point two", results=[])
    with pytest.raises(LogError, match="malformed"):
        list(McapLogReader(junk).frames())


def test_topics_come_from_the_log_and_invalid_messages_are_counted(tmp_path):
    cfg = McapLogConfig(image_topic="/robot/cam", result_topic="/robot/loops", stats_topic="/robot/loops/stats")
    path = tmp_path / "custom.mcap"
    img = sample_images(1, size=(32, 32))[0]
    with McapLogWriter(path, cfg) as w:
        payload, enc = encode_frame(img, "png")
        w.write_image(payload, enc, 7, sequence=0)
        w.write_result(make_result(0, 7))
        w.write_result({"sequence": "not a number", "stamp_ns": 8})  # a hostile writer
        w.write_result(make_result(1, 9), data=b"{truncated")
        w.write_stats(StatsMessage(stamp_ns=1, uptime_s=1.0, frames_received=1, frames_processed=1, dropped=0,
                                   bad={}, loops=0))
    r = McapLogReader(path)
    assert len(list(r.frames())) == 1 and r.status.image_topic == "/robot/cam"
    assert [x.stamp_ns for x in r.results] == [7] and len(r.stats) == 1
    assert r.status.invalid_messages == 2 and "not JSON" in r.status.last_invalid
    meta = read_log_metadata(path)["aefabmap.log"]
    assert meta["result_topic"] == "/robot/loops" and meta["image_topic"] == "/robot/cam"
