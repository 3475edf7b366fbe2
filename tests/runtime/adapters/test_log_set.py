"""Log sets: names, which files are ours, budget trimming, reading order (runtime/aefabmap_runtime/adapters/log_set.py)."""

from __future__ import annotations

import os

import pytest

from aefabmap_runtime.errors import ConfigError, LogError
from aefabmap_runtime.adapters.log_set import (
    LOG_FILE_METADATA,
    MCAP_MAGIC,
    LogSet,
    log_files,
)
from aefabmap_runtime.adapters.mcap_log import McapLogWriter


def _mcap(path, size=100):
    path.write_bytes(MCAP_MAGIC + b"\0" * (size - len(MCAP_MAGIC)))
    return path


def test_plain_target_first_file_is_the_path_then_numbered(tmp_path):
    s = LogSet(tmp_path / "run.mcap")
    assert s.kind == "plain" and s.name_for(0) == "run.mcap" and s.name_for(1) == "run-0001.mcap"
    assert s.name_for(12345) == "run-12345.mcap"
    assert s.first_number() == 0
    _mcap(tmp_path / "run.mcap")
    assert s.first_number() == 1
    _mcap(tmp_path / "run-0003.mcap")
    assert s.first_number() == 4  # after the highest: name order stays creation order
    for foreign in ("run-01.mcap", "run-0001.mcap.bak", "xrun-0009.mcap", "run-abcd.mcap", "run_0009.mcap"):
        assert s.number_of(foreign) is None, foreign
    assert s.number_of("run.mcap") == 0 and s.number_of("run-0003.mcap") == 3


def test_pattern_and_directory_targets(tmp_path):
    p = LogSet(tmp_path / "run-{n}.mcap")
    assert p.kind == "pattern" and p.name_for(1) == "run-0001.mcap" and p.first_number() == 1
    assert p.number_of("run-0042.mcap") == 42 and p.number_of("run.mcap") is None
    d = LogSet(str(tmp_path) + "/")
    assert d.kind == "dir" and d.directory == tmp_path
    name = d.name_for(7, opened_ns=0)
    assert name == "lcd-19700101-000000-0007.mcap" and d.number_of(name) == 7
    assert d.number_of("lcd-1970-0007.mcap") is None and d.number_of("other.mcap") is None
    assert LogSet(tmp_path).kind == "dir"  # an existing directory without the slash
    with pytest.raises(ConfigError, match="one is allowed"):
        LogSet(tmp_path / "a-{n}-{n}.mcap")
    with pytest.raises(ConfigError, match="file name"):
        LogSet(tmp_path / "{n}" / "a.mcap")
    with pytest.raises(LogError, match="does not exist"):
        LogSet(tmp_path / "missing" / "a.mcap").check_writable()


def test_a_missing_directory_target_is_created_a_missing_file_directory_is_refused(tmp_path):
    d = LogSet(f"{tmp_path / 'logs' / 'day1'}/")
    d.make_directory()
    assert (tmp_path / "logs" / "day1").is_dir()
    d.check_writable()
    plain = LogSet(tmp_path / "typo" / "run.mcap")
    plain.make_directory()  # a file target's directory is not created: a typo stays an error
    assert not (tmp_path / "typo").exists()
    with pytest.raises(LogError, match="does not exist"):
        plain.check_writable()
    (tmp_path / "taken").write_text("a file, not a directory")
    with pytest.raises(LogError, match="cannot create the MCAP log directory"):
        LogSet(f"{tmp_path / 'taken' / 'logs'}/").make_directory()


def test_only_our_regular_mcap_files_count_and_the_oldest_go_first(tmp_path):
    s = LogSet(tmp_path / "run.mcap")
    for name in ("run.mcap", "run-0001.mcap", "run-0002.mcap", "run-0003.mcap"):
        _mcap(tmp_path / name, 1000)
    (tmp_path / "run-0004.mcap").write_bytes(b"not an mcap" * 100)  # our name, not our content
    outside = _mcap(tmp_path / "precious.mcap", 1000)
    (tmp_path / "run-0005.mcap").symlink_to(outside)  # never followed, never deleted
    (tmp_path / "run-0006.mcap").mkdir()
    assert [f.path.name for f in s.files()] == ["run.mcap", "run-0001.mcap", "run-0002.mcap", "run-0003.mcap"]
    assert s.first_number() == 7  # a name taken by anything is never reused
    gone = s.trim_to_budget(1500, reserve_bytes=0, keep=tmp_path / "run.mcap")
    assert [f.path.name for f in gone] == ["run-0001.mcap", "run-0002.mcap"]
    assert sorted(os.listdir(tmp_path)) == ["precious.mcap", "run-0003.mcap", "run-0004.mcap", "run-0005.mcap",
                                            "run-0006.mcap", "run.mcap"]
    assert outside.stat().st_size == 1000
    assert s.trim_to_budget(10_000, reserve_bytes=5_000, keep=None) == []  # within budget: nothing


def _log(path, started, index):
    with McapLogWriter(path, extra_metadata={LOG_FILE_METADATA: {"run_started_ns": started, "index": index}}):
        pass
    return path


def test_log_files_expands_dirs_globs_lists_in_run_order(tmp_path):
    d = tmp_path / "logs"
    d.mkdir()
    # names disagree with run order on purpose: run order wins for files of a set
    b2 = _log(d / "a.mcap", 200, 2)
    b1 = _log(d / "b.mcap", 200, 1)
    a1 = _log(d / "c.mcap", 100, 1)
    (d / "notes.txt").write_text("x")
    assert log_files(d) == [a1, b1, b2]
    assert log_files(str(d / "*.mcap")) == [a1, b1, b2]
    assert log_files([b2, a1]) == [a1, b2]
    assert log_files(b2) == [b2]
    with pytest.raises(LogError, match="no files match"):
        log_files(str(d / "*.nothing"))
    with pytest.raises(LogError, match="does not exist"):
        log_files(d / "missing.mcap")
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(LogError, match="no .mcap files"):
        log_files(empty)
