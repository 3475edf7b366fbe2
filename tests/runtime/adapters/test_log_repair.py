"""`aefabmap log repair`: a log cut off by a full disk or a kill -9 made readable by standard
readers, every complete message kept."""

from __future__ import annotations

import json

import pytest
from mcap.reader import make_reader

from aefabmap.cli.main import main
from aefabmap_runtime.errors import LogError
from aefabmap_runtime.adapters.log_repair import repair_log
from aefabmap_runtime.adapters.mcap_log import RUN_CONFIG_METADATA, McapLogConfig, McapLogReader

from .stream_fakes import sample_images
from .test_mcap_log import _write_log

pytestmark = pytest.mark.timeout(60)


def _stock_messages(path) -> int:
    """Messages a standard seeking reader finds (0 when it cannot read the file at all)."""
    with open(path, "rb") as f:
        try:
            return sum(1 for _ in make_reader(f).iter_messages())
        except Exception:
            return 0


def test_a_cut_off_log_is_repaired_for_standard_readers(tmp_path, capsys):
    whole = tmp_path / "whole.mcap"
    _write_log(whole, sample_images(40, size=(160, 120)), config=McapLogConfig(chunk_size=4096))
    data = whole.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * 0.7)])  # the disk filled up here
    assert _stock_messages(cut) == 0  # the attack: a standard reader sees nothing
    ours = McapLogReader(cut)
    frames = list(ours.frames())
    assert ours.status.truncated and frames

    assert main(["log", "repair", str(cut), "--out", str(tmp_path / "fixed.mcap")]) == 0
    report = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert report["truncated"] and report["messages"] > 0
    assert _stock_messages(tmp_path / "fixed.mcap") == report["messages"]
    fixed = McapLogReader(tmp_path / "fixed.mcap")
    assert [f.sequence for f in fixed.frames()] == [f.sequence for f in frames] and not fixed.status.truncated
    assert fixed.metadata[RUN_CONFIG_METADATA] == {"key": "a/b"}  # the run's configuration survives


def test_repair_refuses_a_non_log_and_never_overwrites(tmp_path):
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap file at all")
    with pytest.raises(LogError, match="not an MCAP file"):
        repair_log(junk, tmp_path / "out.mcap")
    assert not (tmp_path / "out.mcap").exists()
    whole = tmp_path / "whole.mcap"
    _write_log(whole, sample_images(2, size=(64, 48)))
    (tmp_path / "taken.mcap").write_bytes(b"keep me")
    with pytest.raises(LogError, match="must not exist"):
        repair_log(whole, tmp_path / "taken.mcap")
    assert (tmp_path / "taken.mcap").read_bytes() == b"keep me"
    assert main(["log", "repair", str(junk), "--out", str(tmp_path / "o.mcap")]) == LogError.exit_code
