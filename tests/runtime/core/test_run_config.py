"""Reading back the run configuration a log recorded, older logs' included (core/run_config.py)."""

import dataclasses
import math

import pytest

from aefabmap_runtime.core.decide.candidates import CandidateConfig
from aefabmap_runtime.core.detector import DetectorConfig
from aefabmap_runtime.core.run_config import RUN_CONFIG_KEY, RunConfig, logged_run_config
from aefabmap_runtime.core.verify.verification import VerificationConfig
from aefabmap_runtime.errors import ConfigError


def _logged(config: RunConfig) -> RunConfig:
    return logged_run_config({RUN_CONFIG_KEY: config.to_dict()})


def test_a_logged_run_config_reads_back_whole():
    config = RunConfig(model="B", queue=4, detector=DetectorConfig(
        exclude=3, candidates=CandidateConfig(top_k=4, bruteforce_fallback=1, track_memory=3),
        verification=VerificationConfig(upright=False)))
    assert _logged(config) == config
    assert _logged(RunConfig()).detector.candidates.track_memory == CandidateConfig().track_memory


def test_logs_written_before_upright_descriptors_replay_without_them():
    doc = RunConfig().to_dict()
    assert logged_run_config({RUN_CONFIG_KEY: doc}).detector.verification.upright
    del doc["detector"]["verification"]["upright"]
    assert not logged_run_config({RUN_CONFIG_KEY: doc}).detector.verification.upright


def test_logs_written_before_the_retry_alone_replay_with_same_word_checks_first():
    doc = RunConfig().to_dict()
    assert logged_run_config({RUN_CONFIG_KEY: doc}).detector.candidates.retry_alone
    del doc["detector"]["candidates"]["retry_alone"]
    assert not logged_run_config({RUN_CONFIG_KEY: doc}).detector.candidates.retry_alone
    assert not logged_run_config({"max_places": 5}).detector.candidates.retry_alone


@pytest.mark.parametrize("section", ["sequence", "candidates"])
def test_logs_written_before_a_margin_replay_without_it(section):
    doc = RunConfig().to_dict()
    assert getattr(logged_run_config({RUN_CONFIG_KEY: doc}).detector, section).margin_log10_nfa == \
        pytest.approx(math.log10(2))
    del doc["detector"][section]["margin_log10_nfa"]
    assert getattr(logged_run_config({RUN_CONFIG_KEY: doc}).detector, section).margin_log10_nfa == 0.0
    assert getattr(logged_run_config({"max_places": 5}).detector, section).margin_log10_nfa == 0.0


def test_logs_written_before_chains_replay_without_them():
    doc = RunConfig(detector=DetectorConfig(sequence=dataclasses.replace(DetectorConfig().sequence, frames=2))).to_dict()
    assert logged_run_config({RUN_CONFIG_KEY: doc}).detector.sequence.frames == 2
    del doc["detector"]["sequence"]
    assert logged_run_config({RUN_CONFIG_KEY: doc}).detector.sequence.frames == 0


def test_logs_written_before_the_whole_config_was_kept_run_as_they_ran():
    legacy = logged_run_config({"max_places": 5, "camera": [500, 500, 320, 240], "model": "old"})
    d = legacy.detector
    assert (legacy.model, d.max_places, d.verification.camera) == ("old", 5, (500.0, 500.0, 320.0, 240.0))
    assert d.sequence.frames == 0 and not d.verification.upright
    assert (d.candidates.bruteforce_fallback, d.candidates.track_memory) == (1, 3)
    assert logged_run_config({}).detector == dataclasses.replace(d, max_places=None, verification=dataclasses.replace(
        d.verification, camera=None))


@pytest.mark.parametrize("record", [[], {RUN_CONFIG_KEY: {"format": 1, "detector": "x"}},
                                    {RUN_CONFIG_KEY: {"format": 99}}, {"max_places": "many"}])
def test_a_malformed_record_is_a_config_error(record):
    with pytest.raises(ConfigError):
        logged_run_config(record)
