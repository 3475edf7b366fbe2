"""Helpers for the tests of deploy/aefabmap.service: read the unit, its `aefabmap run` command
line, and the command prefix that runs a process under the unit's seccomp filters."""

from __future__ import annotations

import ctypes.util
import re
import shlex
import shutil
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
UNIT_PATH = REPO / "deploy" / "aefabmap.service"
SANDBOX = Path(__file__).with_name("unit_sandbox.py")


def read_unit(path: Path = UNIT_PATH) -> dict[str, dict[str, list[str]]]:
    """Parse a unit file into {section: {key: [values in order]}}.

    Backslash-continued lines are joined with a space (as systemd does); comments and blank
    lines are dropped; a key may repeat (SystemCallFilter=, Environment=...), so every value is kept.
    """
    sections: dict[str, dict[str, list[str]]] = {}
    current: dict[str, list[str]] | None = None
    pending = ""
    for raw in path.read_text().splitlines():
        line = raw.strip()
        if not line or line[0] in "#;":  # systemd also skips comments inside a continuation
            continue
        if line.endswith("\\"):
            pending += line[:-1].rstrip() + " "
            continue
        line, pending = pending + line, ""
        if line.startswith("[") and line.endswith("]"):
            current = sections.setdefault(line[1:-1], {})
            continue
        if current is None or "=" not in line:
            raise ValueError(f"{path}: not a unit-file line: {raw!r}")
        key, value = line.split("=", 1)
        current.setdefault(key.strip(), []).append(value.strip())
    return sections


def run_argv(service: dict[str, list[str]]) -> list[str]:
    """The `run ...` arguments of ExecStart (a `/bin/sh -c 'exec .../aefabmap run ...'` wrapper)."""
    exec_start = shlex.split(service["ExecStart"][-1])
    assert exec_start[:2] == ["/bin/sh", "-c"], exec_start
    # systemd turns %% into %; the shell then expands $(date ...): stand a fixed name in for it.
    script = exec_start[2].replace("%%", "%")
    script = re.sub(r"\$\(date [^)]*\)", "20260101T000000Z", script)
    words = shlex.split(script)
    assert words[0] == "exec" and words[1].endswith("/aefabmap") and words[2] == "run", words
    return words[2:]


def sandbox_available() -> bool:
    """unit_sandbox.py needs Linux, libseccomp and systemd-analyze (to expand @groups)."""
    return (sys.platform.startswith("linux") and shutil.which("systemd-analyze") is not None
            and ctypes.util.find_library("seccomp") is not None)


def sandbox_prefix(service: dict[str, list[str]]) -> list[str]:
    """argv prefix running a command under the unit's SystemCallFilter= and MemoryDenyWriteExecute=."""
    assert service["MemoryDenyWriteExecute"] == ["yes"]
    flags: list[str] = []
    for value in service["SystemCallFilter"]:
        for group in value.split():
            flags += ["--deny", group[1:]] if group.startswith("~") else ["--allow", group]
    return [sys.executable, str(SANDBOX), *flags, "--"]
