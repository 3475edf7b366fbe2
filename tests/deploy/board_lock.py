"""Check deploy/requirements-board.txt the way a board's pip sees it, one glibc level at a time.

pip's ``--platform`` matches a wheel tag exactly, so a board with glibc 2.N is modelled by passing
every tag it accepts: ``manylinux2014_aarch64`` (some wheels, e.g. protobuf's, carry only that
legacy name) and ``manylinux_2_17_aarch64`` .. ``manylinux_2_N_aarch64``.
"""

from __future__ import annotations

import re
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

_PIN = re.compile(r"^([A-Za-z0-9._-]+)==(\S+)")
_NOT_FOUND = re.compile(r"No matching distribution found for ([A-Za-z0-9._-]+)==")
# pip also says "No matching distribution" when it could not reach the index: these mean the network.
_NETWORK_TROUBLE = re.compile(r"Retrying \(Retry\(|NewConnectionError|Max retries exceeded|Could not fetch URL|Read timed out")


def read_lock(path: Path) -> dict[str, str]:
    """{package name: its requirement block (the pin line and its --hash lines)} of a hashed lock."""
    blocks: dict[str, list[str]] = {}
    current = None
    for line in path.read_text().splitlines():
        if match := _PIN.match(line):
            current = match.group(1)
            blocks[current] = [line]
        elif current and line.strip().startswith("--hash="):
            blocks[current].append(line)
    return {name: "\n".join(lines) for name, lines in blocks.items()}


def manylinux_tags(glibc_minor: int, arch: str = "aarch64") -> list[str]:
    """Every manylinux platform tag a glibc 2.<glibc_minor> system installs, oldest first."""
    return [f"manylinux2014_{arch}"] + [f"manylinux_2_{k}_{arch}" for k in range(17, glibc_minor + 1)]


@dataclass(frozen=True)
class LevelResult:
    glibc_minor: int
    missing: tuple[str, ...]  # packages of the lock with no installable wheel at this level
    pip_runs: int


def resolve_level(lock: dict[str, str], glibc_minor: int, python: str = "3.11", timeout_s: float = 300) -> LevelResult:
    """`pip download --require-hashes --only-binary=:all:` of the whole lock for one glibc level.

    pip stops at the first requirement it cannot satisfy, so a missing package is noted, dropped
    and the rest tried again until the remainder resolves. Any other pip error (a hash mismatch,
    the network) raises RuntimeError.
    """
    abi = "cp" + python.replace(".", "")
    todo = dict(lock)
    missing: list[str] = []
    runs = 0
    with tempfile.TemporaryDirectory(prefix=f"lock-glibc-2.{glibc_minor}-") as tmp:
        requirements = Path(tmp) / "requirements.txt"
        while todo:
            requirements.write_text("\n".join(todo.values()) + "\n")
            cmd = [
                sys.executable, "-m", "pip", "download", "--quiet", "--disable-pip-version-check",
                "--retries", "2", "--timeout", "30",
                "--only-binary=:all:", "--no-deps", "--require-hashes", "-r", str(requirements),
                "--python-version", python, "--implementation", "cp", "--abi", abi, "-d", str(Path(tmp) / "wheels"),
            ]
            for tag in manylinux_tags(glibc_minor):
                cmd += ["--platform", tag]
            out = subprocess.run(cmd, check=False, capture_output=True, text=True, timeout=timeout_s)
            runs += 1
            if out.returncode == 0:
                break
            match = _NOT_FOUND.search(out.stderr)
            if not match or match.group(1) not in todo or _NETWORK_TROUBLE.search(out.stderr):
                raise RuntimeError(f"pip download failed at glibc 2.{glibc_minor}: {out.stderr.strip()[-2000:]}")
            missing.append(match.group(1))
            del todo[match.group(1)]
    return LevelResult(glibc_minor, tuple(sorted(missing)), runs)


def index_reachable(package: str, version: str, glibc_minor: int = 28, timeout_s: float = 30) -> tuple[bool, str]:
    """Whether pip's index lists `package==version` for aarch64 (the reason if not).

    Reads only the project's index page. --no-cache-dir: pip's HTTP cache answers for pages
    fetched in the last minutes, and a local mirror may hold pure-Python or x86-64 wheels only,
    either of which would make an offline machine look online.
    """
    cmd = [sys.executable, "-m", "pip", "index", "versions", package, "--disable-pip-version-check", "--no-cache-dir",
           "--retries", "0", "--timeout", "10", "--only-binary=:all:", "--python-version", "3.11",
           "--implementation", "cp", "--abi", "cp311", "--platform", f"manylinux_2_{glibc_minor}_aarch64"]
    try:
        out = subprocess.run(cmd, check=False, capture_output=True, text=True, timeout=timeout_s)
    except subprocess.TimeoutExpired:
        return False, f"pip index did not answer within {timeout_s:.0f} s"
    listed = re.search(r"Available versions: (.*)", out.stdout)
    if listed and version in [v.strip() for v in listed.group(1).split(",")]:
        return True, ""
    return False, f"{package}=={version} for aarch64 not listed by the index: {(out.stdout + out.stderr).strip()[-300:]}"
