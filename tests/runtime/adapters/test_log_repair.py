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


def _cli(*args, timeout_s: float = 30):
    """`aefabmap ARGS` as a child process (it must finish within timeout_s: a hang fails the test)."""
    import subprocess

    from .stream_fakes import CLI

    return subprocess.run(CLI + [str(a) for a in args], capture_output=True, text=True, timeout=timeout_s, check=False)


@pytest.mark.parametrize("what", ["fifo", "directory", "device"])
def test_repair_refuses_what_is_not_a_regular_file_without_hanging(tmp_path, what):
    """The attack: `log repair` given a FIFO with no writer blocked in open() for ever, with no message."""
    import os

    source = tmp_path / "in.mcap"
    if what == "fifo":
        os.mkfifo(source)
    elif what == "directory":
        source.mkdir()
    else:
        source = "/dev/zero"
    done = _cli("log", "repair", source, "--out", tmp_path / "out.mcap")
    assert done.returncode == LogError.exit_code, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in done.stderr
    assert f"{source} is not a regular file" in lines[0]
    assert not (tmp_path / "out.mcap").exists()


def test_repair_onto_a_full_disk_says_so_and_leaves_no_partial_file(tmp_path):
    """A real small disk (tmpfs; skipped where it cannot be mounted) too small for the repaired log:
    one line naming the output and the full disk, no partial output left, the input untouched."""
    import numpy as np

    from .stream_fakes import mounted_tmpfs

    rng = np.random.default_rng(0)
    noise = [rng.integers(0, 256, (240, 320), dtype=np.uint8) for _ in range(12)]  # incompressible
    whole = tmp_path / "whole.mcap"
    _write_log(whole, noise)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(whole.read_bytes()[: int(whole.stat().st_size * 0.8)])
    before = cut.read_bytes()
    disk = tmp_path / "disk"
    disk.mkdir()
    with mounted_tmpfs(disk, size="128k"):
        out = disk / "fixed.mcap"
        done = _cli("log", "repair", cut, "--out", out)
        assert done.returncode == LogError.exit_code, done.stderr
        lines = done.stderr.strip().splitlines()
        assert len(lines) == 1 and "Traceback" not in done.stderr, done.stderr
        assert str(out) in lines[0] and "disk is full" in lines[0]
        assert not out.exists() and not list(disk.iterdir())
    assert cut.read_bytes() == before
