"""The shared options (aefabmap/cli/options.py): each declared once, read into a RunConfig."""

import argparse

import pytest

from aefabmap.cli.main import build_parser
from aefabmap.cli.options import EXIT_CODES, build_run_config
from aefabmap_runtime.core.run_config import RUN_CONFIG_KEY, RunConfig, logged_run_config
from aefabmap_runtime.errors import ConfigError

VERIFY = ("--verify-keypoints", "--verify-bruteforce", "--no-verify-upright")


def _run(*extra: str) -> RunConfig:
    return build_run_config(build_parser().parse_args(["run", "--model", "B", "--key", "k", "--mcap", "x.mcap", *extra]))


def test_sequence_frames_option():
    assert _run().detector.sequence.frames == 2
    assert _run("--sequence-frames", "0").detector.sequence.frames == 0
    assert _run("--sequence-frames", "3").detector.sequence.frames == 3
    with pytest.raises(ConfigError, match="sequence frames"):
        _run("--sequence-frames", "1")


@pytest.mark.parametrize("option, section", [("--sequence-margin", "sequence"), ("--pair-margin", "candidates")])
def test_margin_options_let_a_map_journalled_before_them_replay(option, section):
    import json
    import math

    from aefabmap_runtime.core.run_config import recorded_settings_differences

    assert getattr(_run().detector, section).margin_log10_nfa == pytest.approx(math.log10(2))
    before = _run(option, "0").detector
    assert getattr(before, section).margin_log10_nfa == 0.0
    # A map state or journal written before the margin existed records no margin.
    recorded = before.to_dict()
    del recorded[section]["margin_log10_nfa"]
    assert recorded_settings_differences(json.dumps(recorded), before) == []
    assert recorded_settings_differences(json.dumps(recorded), _run().detector) == [f"{section}.margin_log10_nfa"]
    with pytest.raises(ConfigError, match="margin"):
        _run(option, "-1")


def test_verify_bruteforce_option_sets_the_retried_candidates_and_is_logged_whole():
    assert _run().detector.candidates.bruteforce_fallback == 5  # every FAB-MAP candidate of the top 5
    cfg = _run("--verify-bruteforce", "1", "--verify-top-k", "4")
    assert (cfg.detector.candidates.bruteforce_fallback, cfg.detector.candidates.top_k) == (1, 4)
    assert logged_run_config({RUN_CONFIG_KEY: cfg.to_dict()}).detector.candidates.bruteforce_fallback == 1
    with pytest.raises(ConfigError, match="bruteforce_fallback"):
        _run("--verify-bruteforce", "-1")


def test_track_direction_option_lets_a_map_journalled_before_it_replay():
    import json

    from aefabmap_runtime.core.run_config import recorded_settings_differences

    assert _run().detector.candidates.track_direction
    before = _run("--verify-track-forwards").detector
    assert not before.candidates.track_direction
    recorded = before.to_dict()
    del recorded["candidates"]["track_direction"]  # a map or log recorded before the track learnt a direction
    assert recorded_settings_differences(json.dumps(recorded), before) == []
    assert recorded_settings_differences(json.dumps(recorded), _run().detector) == ["candidates.track_direction"]
    logged = logged_run_config({RUN_CONFIG_KEY: {**_run().to_dict(), "detector": recorded}})
    assert not logged.detector.candidates.track_direction


def test_track_memory_option():
    assert _run().detector.candidates.track_memory == 6
    assert _run("--verify-track-memory", "3").detector.candidates.track_memory == 3
    with pytest.raises(ConfigError, match="track_memory"):
        _run("--verify-track-memory", "0")


def test_upright_option():
    assert _run().detector.verification.upright
    assert not _run("--no-verify-upright").detector.verification.upright


def _actions(*command: str) -> dict[str, argparse.Action]:
    """The option strings of a (sub)command's parser -> their actions."""
    parser = build_parser()
    for name in command:
        parser = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices[name]
    return {s: a for a in parser._actions for s in a.option_strings}


@pytest.mark.parametrize("command", [("run",), ("eval",), ("bench", "sequence"), ("bench", "pipeline")])
def test_the_verification_options_are_the_same_option_in_every_command(command):
    reference, here = _actions("run"), _actions(*command)
    for flag in VERIFY:
        if flag == "--no-verify-upright" and command == ("bench", "pipeline"):
            assert flag not in here
            continue
        a, b = reference[flag], here[flag]
        assert (a.dest, a.type, a.default, a.const, a.metavar, type(a)) == (b.dest, b.type, b.default, b.const,
                                                                            b.metavar, type(b)), flag


def test_every_command_help_ends_with_the_exit_codes(capsys):
    for command in ("run", "replay", "publish", "bench"):
        with pytest.raises(SystemExit):
            build_parser().parse_args([command, "--help"])
        assert " ".join(capsys.readouterr().out.split()).endswith(" ".join(EXIT_CODES.split()))
