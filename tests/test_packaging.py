"""Packaging facts a user relies on: `python -m aefabmap`, one version, a licence that matches the
metadata, and the README's library example working from an installed wheel."""

from __future__ import annotations

import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

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


def readme_library_example() -> str:
    """The README's first python block (its library example)."""
    block = re.search(r"```python\n(.*?)```", (REPO / "README.md").read_text(), re.S)
    assert block, "README has no python example"
    return block.group(1)


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_readme_library_example_runs_from_the_installed_wheel(runtime_install, tmp_path):
    """Installed from the wheel, run in an empty folder outside the checkout: nothing of the
    repository's layout (a relative bundle path) may leak into the example."""
    example, cwd = tmp_path / "example.py", tmp_path / "empty"
    example.write_text(readme_library_example())
    cwd.mkdir()
    proc = runtime_install.run([str(runtime_install.python), str(example)], cwd=cwd)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert re.search(r"frame \d+: revisits frame \d+", proc.stdout), proc.stdout[-2000:]
