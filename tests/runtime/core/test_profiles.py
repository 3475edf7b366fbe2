"""Run profiles: the board preset, its bundle check, and how `aefabmap run --profile` applies it."""

from __future__ import annotations

import argparse

import pytest

from aefabmap.cli.main import build_parser
from aefabmap.cli.options import build_run_config
from aefabmap_runtime.errors import ConfigError
from aefabmap_runtime.core.profiles import PROFILES, get_profile


FLAT = {"type": "kmeans"}


def _manifest(kind="orb", keypoints=500, words=3000, quantizer=None) -> dict:
    return {"features": {"kind": kind, "max_features": keypoints}, "vocabulary_size": words,
            "quantizer": quantizer or FLAT}


def test_board_profile_is_the_documented_preset():
    board = get_profile("board")
    assert (board.feature_kind, board.keypoints, board.words, board.variant) == ("orb", 500, 3000, "kmeans-flat")
    assert (board.threads, board.memory_mb, board.queue) == (1, 64.0, 2)
    with pytest.raises(ConfigError, match="profile must be one of"):
        get_profile("desktop")


def test_board_profile_accepts_its_model_and_refuses_others():
    board = PROFILES["board"]
    board.check_bundle(_manifest())
    board.check_bundle(_manifest(quantizer={"type": "kmeans", "index": {"buckets": 32}}))  # runs it flat
    for manifest in [_manifest(words=2000), _manifest(keypoints=1000),
                     _manifest(kind="sift"), _manifest(quantizer={"type": "kmeans-tree"}), _manifest(quantizer={"type": "ae"})]:
        with pytest.raises(ConfigError, match="Train one with: aefabmap train"):
            board.check_bundle(manifest)


def _run_args(*extra: str) -> argparse.Namespace:
    return build_parser().parse_args(["run", "--model", "B", "--key", "k", "--mcap", "x.mcap", *extra])


def test_run_selects_the_profile_and_explicit_options_win():
    def settings(config):
        d = config.detector
        return {"profile": config.profile, "memory_mb": d.memory_mb, "queue": config.queue, "threads": d.threads,
                "quantizer_variant": d.quantizer_variant}

    plain = settings(build_run_config(_run_args()))
    assert plain == {"profile": None, "memory_mb": None, "queue": 2, "threads": 1, "quantizer_variant": "fp32"}
    board = settings(build_run_config(_run_args("--profile", "board")))
    assert board == {"profile": "board", "memory_mb": 64.0, "queue": 2, "threads": 1, "quantizer_variant": "flat"}
    mine = settings(build_run_config(_run_args("--profile", "board", "--memory-mb", "32", "--queue", "4")))
    assert (mine["memory_mb"], mine["queue"]) == (32.0, 4)


def test_unknown_profile_is_a_usage_error():
    with pytest.raises(SystemExit):
        _run_args("--profile", "desktop")


def test_run_refuses_a_bundle_that_is_not_the_profiles_model(tmp_path, synthetic_bundle):
    from aefabmap.cli.main import main

    code = main(["run", "--model", str(synthetic_bundle), "--key", "robot/cam/image", "--mcap", str(tmp_path / "x.mcap"),
                 "--profile", "board"])
    assert code == ConfigError.exit_code
