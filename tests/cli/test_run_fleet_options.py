"""`run --fleet/--robot`: a bad name is one line and exit code 2, before any network or model."""

from __future__ import annotations

import subprocess
import sys

import pytest


@pytest.mark.parametrize("args", [["--fleet", "a/b", "--robot", "x"], ["--fleet", "lab", "--robot", "**"],
                                  ["--fleet", "lab"]])
def test_bad_fleet_options_are_one_line_and_exit_2(tmp_path, args):
    out = subprocess.run([sys.executable, "-m", "aefabmap.cli.main", "run", "--model", str(tmp_path / "none"),
                          "--key", "r/camera/image", "--mcap", str(tmp_path / "x.mcap"), *args],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 2, out.stderr
    errors = [line for line in out.stderr.splitlines() if line.startswith("ERROR")]
    assert len(errors) == 1 and ("fleet" in errors[0] or "robot" in errors[0]), out.stderr
    assert "Traceback" not in out.stderr
