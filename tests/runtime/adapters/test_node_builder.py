"""A node built from its RunConfig (runtime/aefabmap_runtime/adapters/node_builder.py): the shipped
bundle on synthetic frames over loopback Zenoh, its map kept in a state directory, its whole
configuration in the log; what a start that fails had opened is closed again."""

from __future__ import annotations

import dataclasses
import threading

import pytest

from aefabmap.cli.options import default_bundle
from aefabmap_runtime.adapters.mcap_log import RUN_CONFIG_METADATA, McapLogReader
from aefabmap_runtime.adapters.node_builder import NodeIO, run_configured_node
from aefabmap_runtime.adapters.node_session import Endpoints
from aefabmap_runtime.adapters.replay_builder import ConfiguredReplay, ReplayIO
from aefabmap_runtime.adapters.state_dir import MapStateDir, SnapshotPolicy
from aefabmap_runtime.adapters.zenoh_transport import open_session
from aefabmap_runtime.core.detector import DetectorConfig
from aefabmap_runtime.core.run_config import RunConfig, logged_run_config
from aefabmap_runtime.errors import ConfigError, LogError, StateError
from aefabmap_runtime.tools.publisher import array_source, publish_frames

from .stream_fakes import KEY, RESULTS, JsonCollector, sample_images, session_pair

pytestmark = pytest.mark.timeout(180)

CONFIG = RunConfig(model=str(default_bundle()), detector=DetectorConfig(exclude=2), queue=16)


class BuiltNode:
    """run_configured_node in a thread; ready once subscribed (or failed)."""

    def __init__(self, config: RunConfig, io: NodeIO) -> None:
        self.stop, self.ready = threading.Event(), threading.Event()
        self.run = self.error = None

        def target() -> None:
            try:
                self.run = run_configured_node(config, io, stop_event=self.stop, ready_event=self.ready)
            except BaseException as exc:  # noqa: BLE001 - reported to the test
                self.error = exc
            finally:
                self.ready.set()

        self.thread = threading.Thread(target=target, daemon=True)
        self.thread.start()
        assert self.ready.wait(60), "node did not become ready"

    def finish(self):
        self.stop.set()
        self.thread.join(60)
        assert not self.thread.is_alive(), "node did not stop"
        if self.error is not None:
            raise self.error
        return self.run


def _feed(io: NodeIO, connect, images) -> None:
    """Publish `images` to the node and wait for the result of the last one."""
    with open_session(connect) as s:
        results = JsonCollector(s, RESULTS)
        pub = publish_frames(connect, KEY, array_source(images, "jpeg"), rate_hz=20, wait_for_subscriber_s=30)
        assert pub.matched and pub.published == len(images)
        results.wait_for(lambda d: d["frame_seq"] == len(images) - 1, timeout_s=60)
        results.close()


def _run_metadata(path) -> dict:
    reader = McapLogReader(path)
    for _ in reader.frames():
        pass
    return reader.metadata[RUN_CONFIG_METADATA]


def test_a_built_node_keeps_its_map_logs_its_config_and_replays_as_it_ran(tmp_path):
    listen, connect = session_pair()
    io = NodeIO(mcap=tmp_path / "first.mcap", key=KEY, endpoints=Endpoints(listen=listen.listen),
                state=tmp_path / "state", snapshots=SnapshotPolicy(seconds=None, places=3), stats_period_s=0.2)
    images = sample_images(16, size=(160, 120))

    node = BuiltNode(CONFIG, io)
    _feed(io, connect, images[:8])
    first = node.finish()
    assert first.summary.frames_processed == 8 and first.state.frames_kept == 8
    assert first.to_dict()["state"] == first.state.to_dict()
    meta = _run_metadata(tmp_path / "first.mcap")
    assert logged_run_config(meta) == CONFIG and meta["map_start"] == {"frame": 0, "places": 0}

    # The next run continues the map from the state directory, and says where it started.
    io = dataclasses.replace(io, mcap=tmp_path / "second.mcap")
    node = BuiltNode(CONFIG, io)
    _feed(io, connect, images[8:])
    second = node.finish()
    assert second.state.frames_processed == 16 and second.state.frames_not_written == 0
    assert _run_metadata(tmp_path / "second.mcap")["map_start"]["frame"] == 8

    # Both logs as one set, replayed with the logged configuration: the same decisions.
    replay_io = ReplayIO(logs=(str(tmp_path / "first.mcap"), str(tmp_path / "second.mcap")),
                         model=str(default_bundle()), check=True)
    with ConfiguredReplay(replay_io, threading.Event()) as replayer:
        summary = replayer.replay()
    assert summary.frames_processed == 16 and summary.check.ok, summary.check.describe()


def test_a_bundle_that_is_not_the_profile_s_model_fails_before_anything_opens(tmp_path):
    io = NodeIO(mcap=tmp_path / "x.mcap", key=KEY, state=tmp_path / "state")
    with pytest.raises(ConfigError, match="Train one with"):
        run_configured_node(dataclasses.replace(CONFIG, profile="board"), io, stop_event=threading.Event())
    assert not (tmp_path / "x.mcap").exists() and not (tmp_path / "state").exists()


def test_a_failed_start_closes_the_state_directory_it_opened(tmp_path):
    listen, _ = session_pair()
    (tmp_path / "file").write_text("not a directory")
    io = NodeIO(mcap=tmp_path / "file" / "x.mcap", key=KEY, endpoints=Endpoints(listen=listen.listen),
                state=tmp_path / "state")
    with pytest.raises(LogError):
        run_configured_node(CONFIG, io, stop_event=threading.Event())
    MapStateDir(tmp_path / "state", "any").open().close()  # not locked any more

    io = dataclasses.replace(io, mcap=tmp_path / "x.mcap")
    with MapStateDir(tmp_path / "state", "any"), pytest.raises(StateError, match="in use by another process"):
        run_configured_node(CONFIG, io, stop_event=threading.Event())
    assert not (tmp_path / "x.mcap").exists()


def test_a_node_reads_exactly_one_of_a_key_and_a_ros_topic(tmp_path):
    from aefabmap_runtime.adapters.rmw_zenoh import RosOptions

    with pytest.raises(ConfigError, match="exactly one"):
        NodeIO(mcap=tmp_path / "x.mcap")
    with pytest.raises(ConfigError, match="exactly one"):
        NodeIO(mcap=tmp_path / "x.mcap", key=KEY, ros=RosOptions(topic="/camera/image_raw"))


def test_a_log_that_stops_for_lack_of_free_space_says_so_once_at_warning(tmp_path, caplog):
    """The attack: a log that stopped for lack of free space said so only in the INFO stats line.
    The disk's real free space (os.statvfs) is below thresholds no disk reaches."""
    import logging

    from aefabmap_runtime.adapters.rotating_log import LogRotationConfig

    listen, connect = session_pair()
    io = NodeIO(mcap=tmp_path / "x.mcap", key=KEY, endpoints=Endpoints(listen=listen.listen), stats_period_s=0.2,
                log_rotation=LogRotationConfig(images_min_free_mb=1e12, results_min_free_mb=1e12))
    with caplog.at_level(logging.INFO, logger="aefabmap.run"):
        node = BuiltNode(CONFIG, io)
        _feed(io, connect, sample_images(3, size=(160, 120)))
        node.finish()
    warned = [r.getMessage() for r in caplog.records if r.name == "aefabmap.run" and r.levelno == logging.WARNING]
    assert len(warned) == 1 and "free space" in warned[0] and "nothing is logged" in warned[0], warned
