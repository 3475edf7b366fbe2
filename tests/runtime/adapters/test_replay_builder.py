"""A replay built from its log's RunConfig (runtime/aefabmap_runtime/adapters/replay_builder.py):
the shipped bundle over a log of synthetic frames, with the logged settings, its map saved to a
state directory that the next replay continues; what a start that fails had opened is closed."""

from __future__ import annotations

import threading

import cv2
import pytest

from aefabmap.cli.options import default_bundle
from aefabmap_runtime.adapters import bundle_reader
from aefabmap_runtime.adapters.mcap_log import McapLogWriter
from aefabmap_runtime.adapters.replay_builder import ConfiguredReplay, ReplayIO
from aefabmap_runtime.adapters.state_dir import MapStateDir
from aefabmap_runtime.core.detector import DetectorConfig
from aefabmap_runtime.core.run_config import RUN_CONFIG_KEY, RunConfig
from aefabmap_runtime.errors import BundleError, StateError

from .stream_fakes import sample_images

pytestmark = pytest.mark.timeout(120)

LOGGED = RunConfig(detector=DetectorConfig(exclude=3, max_places=50))


def _log(path, images, first: int = 0):
    """A log of `images` (PNG) by a run of LOGGED."""
    with McapLogWriter(path, run_config={RUN_CONFIG_KEY: LOGGED.to_dict()}) as log:
        for i, img in enumerate(images, start=first):
            log.write_image(cv2.imencode(".png", img)[1].tobytes(), "image/png",
                            1_700_000_000_000_000_000 + i * 100_000_000, sequence=i)
    return str(path)


@pytest.fixture
def loaded_configs(monkeypatch):
    """The DetectorConfigs the replays load the bundle with."""
    configs, real = [], bundle_reader.load_detector
    monkeypatch.setattr(bundle_reader, "load_detector", lambda path, config: configs.append(config) or real(path, config))
    return configs


def test_a_replay_runs_as_the_log_s_run_and_continues_the_map_of_its_state(tmp_path, loaded_configs):
    images = sample_images(12, size=(160, 120))
    first, second = _log(tmp_path / "a.mcap", images[:6]), _log(tmp_path / "b.mcap", images[6:], first=6)
    io = ReplayIO(logs=(first,), model=str(default_bundle()), state=str(tmp_path / "state"),
                  out=str(tmp_path / "a_out.mcap"))
    stop = threading.Event()
    with ConfiguredReplay(io, stop) as replayer:
        summary = replayer.replay()
        MapStateDir(tmp_path / "state", "any").open().close()  # saved and released before any serving
        replayer.serve_until_stopped()  # no view, no fleet: returns at once
    assert summary.frames_processed == 6 and (tmp_path / "a_out.mcap").is_file()
    assert loaded_configs[0] == LOGGED.detector

    with ConfiguredReplay(ReplayIO(logs=(second,), model=str(default_bundle()), state=str(tmp_path / "state")),
                          stop) as replayer:
        assert replayer.detector.next_sequence == 6  # the first replay's map
        assert replayer.replay().frames_processed == 6
        assert replayer.detector.next_sequence == 12


def test_a_failed_start_closes_what_it_opened(tmp_path):
    log = _log(tmp_path / "a.mcap", sample_images(2, size=(160, 120)))
    with pytest.raises(BundleError):
        ConfiguredReplay(ReplayIO(logs=(log,), model=str(tmp_path / "none"), state=str(tmp_path / "state")),
                         threading.Event()).__enter__()
    assert not (tmp_path / "state").exists()  # the bundle is loaded before the state opens
    io = ReplayIO(logs=(log,), model=str(default_bundle()), state=str(tmp_path / "state"))
    with MapStateDir(tmp_path / "state", "any"), pytest.raises(StateError, match="in use"):
        ConfiguredReplay(io, threading.Event()).__enter__()
    with ConfiguredReplay(io, threading.Event()) as replayer:  # nothing left locked
        assert replayer.replay().frames_processed == 2
