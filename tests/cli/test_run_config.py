"""The run configuration a command builds from options and reads back from a log."""

import pytest

from aefabmap.cli.main import build_parser
from aefabmap.cli.run_config import RUN_CONFIG_KEY, build_run_config, logged_run_config
from aefabmap_runtime.errors import ConfigError
from aefabmap_runtime.core.run_config import RunConfig


def _run(*extra: str) -> RunConfig:
    return build_run_config(build_parser().parse_args(["run", "--model", "B", "--key", "k", "--mcap", "x.mcap", *extra]))


def test_sequence_frames_option():
    assert _run().detector.sequence.frames == 2
    assert _run("--sequence-frames", "0").detector.sequence.frames == 0
    assert _run("--sequence-frames", "3").detector.sequence.frames == 3
    with pytest.raises(ConfigError, match="sequence frames"):
        _run("--sequence-frames", "1")


def test_verify_bruteforce_option_sets_the_retried_candidates_and_is_logged_whole():
    assert _run().detector.candidates.bruteforce_fallback == 5  # every FAB-MAP candidate of the top 5
    cfg = _run("--verify-bruteforce", "1", "--verify-top-k", "4")
    assert (cfg.detector.candidates.bruteforce_fallback, cfg.detector.candidates.top_k) == (1, 4)
    assert logged_run_config({RUN_CONFIG_KEY: cfg.to_dict()}).detector.candidates.bruteforce_fallback == 1
    with pytest.raises(ConfigError, match="bruteforce_fallback"):
        _run("--verify-bruteforce", "-1")


def test_track_memory_option_and_logs_written_before_the_whole_config_kept_three():
    assert _run().detector.candidates.track_memory == 6
    cfg = _run("--verify-track-memory", "3")
    assert cfg.detector.candidates.track_memory == 3
    assert logged_run_config({RUN_CONFIG_KEY: cfg.to_dict()}).detector.candidates.track_memory == 3
    assert logged_run_config({RUN_CONFIG_KEY: _run().to_dict()}).detector.candidates.track_memory == 6
    assert logged_run_config({"max_places": 5}).detector.candidates.track_memory == 3
    with pytest.raises(ConfigError, match="track_memory"):
        _run("--verify-track-memory", "0")


def test_upright_option_and_logs_written_before_it_replay_without_it():
    assert _run().detector.verification.upright
    cfg = _run("--no-verify-upright")
    assert not cfg.detector.verification.upright
    assert not logged_run_config({RUN_CONFIG_KEY: cfg.to_dict()}).detector.verification.upright
    doc = _run().to_dict()
    assert logged_run_config({RUN_CONFIG_KEY: doc}).detector.verification.upright
    del doc["detector"]["verification"]["upright"]
    assert not logged_run_config({RUN_CONFIG_KEY: doc}).detector.verification.upright
    assert not logged_run_config({"max_places": 5}).detector.verification.upright


def test_logs_written_before_chains_replay_without_them():
    doc = _run().to_dict()
    assert logged_run_config({RUN_CONFIG_KEY: doc}).detector.sequence.frames == 2
    del doc["detector"]["sequence"]
    assert logged_run_config({RUN_CONFIG_KEY: doc}).detector.sequence.frames == 0
    legacy = logged_run_config({"max_places": 5}).detector  # before the whole config was kept
    assert legacy.sequence.frames == 0 and legacy.candidates.bruteforce_fallback == 1
    with pytest.raises(ConfigError):
        logged_run_config({RUN_CONFIG_KEY: {**doc, "detector": "x"}})
