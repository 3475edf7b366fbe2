"""Packaging facts a user relies on: `python -m aefabmap`, one version, a licence that matches the metadata."""

from __future__ import annotations

import subprocess
import sys
import tomllib
from pathlib import Path

import aefabmap

REPO = Path(__file__).resolve().parents[1]


def _pyproject() -> dict:
    return tomllib.loads((REPO / "pyproject.toml").read_text())


def test_python_m_aefabmap_runs_the_cli():
    out = subprocess.run([sys.executable, "-m", "aefabmap", "--version"], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert aefabmap.__version__ in out.stdout + out.stderr


def test_version_is_written_once():
    project = _pyproject()["project"]
    assert "version" not in project and "version" in project["dynamic"]
    assert _pyproject()["tool"]["setuptools"]["dynamic"]["version"] == {"attr": "aefabmap_runtime.version.__version__"}
    assert "__version__ =" not in (REPO / "aefabmap" / "__init__.py").read_text()  # re-exported, not written again


def test_licence_file_matches_the_metadata():
    project = _pyproject()["project"]
    assert project["license"] == "BSD-3-Clause"
    assert project["license-files"] == ["LICENSE"]
    assert (REPO / "LICENSE").read_text().startswith("BSD 3-Clause License")


def test_python_version_is_stated_consistently():
    assert _pyproject()["project"]["requires-python"] == ">=3.11"
    assert "Python >= 3.11" in (REPO / "deploy" / "README.md").read_text()
    assert sys.version_info >= (3, 11)
