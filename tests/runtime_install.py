"""A real runtime-only install for tests: this checkout built as a wheel and installed, with the
runtime dependencies only (no extra), into a fresh venv, as `pip install aefabmap` on a board.

The wheel is built from a copy of the working tree (the build writes build/ and *.egg-info, which
must not land in a checkout others work in). Dependencies come from the package index at the
versions of constraints.txt; pip's own cache keeps a second build fast.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
#: Left out of the copy the wheel is built from: environments, caches, build outputs, and compiled
#: kernels (the build compiles its own).
NOT_SOURCES = (".venv", ".git", "build", "dist", "*.egg-info", "__pycache__", ".pytest_cache", "*.so")
#: Import names of the `train` extra's packages (pyproject.toml): a runtime-only install lacks them.
ABSENT_FROM_RUNTIME = ("torch", "onnx", "onnxscript", "scipy", "matplotlib")


@dataclass(frozen=True)
class RuntimeInstall:
    """A venv holding the installed wheel. python / aefabmap: its interpreter and console script."""

    venv: Path

    @property
    def python(self) -> Path:
        return self.venv / "bin" / "python"

    @property
    def aefabmap(self) -> Path:
        return self.venv / "bin" / "aefabmap"

    def env(self) -> dict[str, str]:
        """The environment to run it in: this venv first on PATH, nothing pointing at the checkout."""
        env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")}
        env["PATH"] = f"{self.venv / 'bin'}{os.pathsep}{env.get('PATH', '')}"
        env["PYTHONNOUSERSITE"] = "1"
        return env

    def run(self, argv: list[str], cwd: Path, timeout: float = 240) -> subprocess.CompletedProcess:
        return subprocess.run(argv, capture_output=True, text=True, timeout=timeout, cwd=cwd, env=self.env())


def _pip(*args: str, timeout: float) -> None:
    proc = subprocess.run([sys.executable, "-m", "pip", *args], capture_output=True, text=True, timeout=timeout)
    if proc.returncode != 0:
        raise RuntimeError(f"pip {' '.join(args[:2])} failed:\n{proc.stderr[-3000:]}")


def build_runtime_install(work: Path) -> RuntimeInstall:
    """Build the wheel of this checkout and install it, runtime dependencies only, into work/venv."""
    source, dist, venv = work / "src", work / "dist", work / "venv"
    shutil.copytree(REPO, source, ignore=shutil.ignore_patterns(*NOT_SOURCES))
    # The build backend of this venv (setuptools) builds it: no second download of the backend.
    _pip("wheel", "--no-deps", "--no-build-isolation", "-q", "-w", str(dist), str(source), timeout=300)
    (wheel,) = dist.glob("aefabmap-*.whl")
    # No pip inside the venv: this venv's pip installs into it (--python), which saves bootstrapping one.
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True, timeout=120)
    install = RuntimeInstall(venv)
    _pip("--python", str(install.python), "install", "-q", "-c", str(REPO / "constraints.txt"), str(wheel),
         timeout=600)
    present = install.run([str(install.python), "-c", "import importlib.util as u, sys; "
                           f"print(' '.join(m for m in {ABSENT_FROM_RUNTIME!r} if u.find_spec(m)))"], cwd=work)
    if present.returncode != 0 or present.stdout.strip():
        raise RuntimeError(f"the runtime-only venv is not runtime-only: {present.stdout.strip()} {present.stderr[-500:]}")
    return install
