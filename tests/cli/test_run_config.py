"""The run configuration a command builds from options and reads back from a log."""

import pytest

from aefabmap.cli.main import build_parser
from aefabmap.cli.run_config import RUN_CONFIG_KEY, build_run_config, logged_run_config
from aefabmap.errors import ConfigError
from aefabmap.runtime.core.run_config import RunConfig


def _run(*extra: str) -> RunConfig:
    return build_run_config(build_parser().parse_args(["run", "--model", "B", "--key", "k", "--mcap", "x.mcap", *extra]))


def test_sequence_frames_option():
    assert _run().detector.sequence.frames == 2
    assert _run("--sequence-frames", "0").detector.sequence.frames == 0
    assert _run("--sequence-frames", "3").detector.sequence.frames == 3
    with pytest.raises(ConfigError, match="sequence frames"):
        _run("--sequence-frames", "1")


def test_logs_written_before_chains_replay_without_them():
    doc = _run().to_dict()
    assert logged_run_config({RUN_CONFIG_KEY: doc}).detector.sequence.frames == 2
    del doc["detector"]["sequence"]
    assert logged_run_config({RUN_CONFIG_KEY: doc}).detector.sequence.frames == 0
    assert logged_run_config({"max_places": 5}).detector.sequence.frames == 0  # before the whole config was kept
    with pytest.raises(ConfigError):
        logged_run_config({RUN_CONFIG_KEY: {**doc, "detector": "x"}})
