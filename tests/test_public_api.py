"""The public API: `from aefabmap import ...` and the README's library example, with nothing of
the trainer (torch, onnx) or the transport (zenoh, mcap) importable, as on a board."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

BLOCKER = textwrap.dedent(
    """
    import sys
    BLOCKED = ('torch', 'onnx', 'onnxscript', 'scipy', 'matplotlib', 'zenoh', 'mcap')
    class Block:
        def find_spec(self, name, path=None, target=None):
            if name.split('.')[0] in BLOCKED:
                raise ImportError(f'{name} is not installed here')
    sys.meta_path.insert(0, Block())
    """
)


def _run(code: str, cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.run([sys.executable, "-c", BLOCKER + code], capture_output=True, text=True, timeout=240,
                          cwd=cwd, env=env)


def test_public_names_import_without_trainer_or_transport(tmp_path):
    proc = _run(textwrap.dedent(
        """
        import aefabmap
        from aefabmap import LoopClosureDetector, DetectorConfig, load_detector, FrameResult, RunConfig
        from aefabmap import AefabmapError, BundleError, ConfigError, InputError, StateError
        for name in aefabmap.__all__:
            getattr(aefabmap, name)
        assert issubclass(BundleError, AefabmapError)
        print('ok')
        """), tmp_path)
    assert proc.returncode == 0 and proc.stdout.strip() == "ok", proc.stderr[-2000:]


def test_unknown_public_name_is_an_attribute_error():
    import aefabmap

    with pytest.raises(AttributeError):
        aefabmap.NoSuchThing  # noqa: B018


@pytest.mark.timeout(300)
def test_readme_library_example_runs(tmp_path):
    text = (REPO / "README.md").read_text()
    block = re.search(r"```python\n(.*?)```", text, re.S)
    assert block, "README has no python example"
    proc = _run(block.group(1), tmp_path)  # a scratch folder: nothing of the checkout's layout at hand
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert re.search(r"frame \d+: revisits frame \d+", proc.stdout), proc.stdout[-2000:]
