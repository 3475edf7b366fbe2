"""The board's install has no torch, onnx, scipy or matplotlib: the runtime commands must not need them."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import numpy as np
import pytest

from aefabmap_runtime.tools.synthetic_route import SyntheticConfig, make_demo_sequence
from tests.conftest import make_synthetic_bundle

BLOCKER = textwrap.dedent(
    """
    import sys
    class Block:
        def find_spec(self, name, path=None, target=None):
            if name.split('.')[0] in ('torch', 'onnx', 'onnxscript', 'scipy', 'matplotlib'):
                raise ImportError(f'{name} is not installed on the board')
    sys.meta_path.insert(0, Block())
    """
)


@pytest.mark.timeout(300)
def test_eval_runs_without_trainer_packages(tmp_path):
    bundle = make_synthetic_bundle(tmp_path / "bundle", vocabulary_size=64)
    seq = tmp_path / "seq"
    make_demo_sequence(seq, n_frames=12, seed=1, size=(160, 120), config=SyntheticConfig(laps=2))
    out = tmp_path / "eval.json"
    code = BLOCKER + textwrap.dedent(
        f"""
        from aefabmap.cli.main import main
        rc = main(['eval', '--model', r'{bundle}', '--images', r'{seq}', '--gt', r'{seq / "gt.npy"}',
                   '--exclude', '2', '--json', r'{out}', '--score-matrix', r'{tmp_path / "m.png"}', '--no-progress'])
        bad = [m for m in ('torch', 'onnx', 'scipy', 'matplotlib') if m in sys.modules]
        assert not bad, bad
        sys.exit(rc)
        """
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=240)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert out.is_file() and (tmp_path / "m.png").is_file()


@pytest.mark.timeout(120)
def test_plot_without_matplotlib_is_a_clear_error(tmp_path):
    bundle = make_synthetic_bundle(tmp_path / "bundle", vocabulary_size=64)
    seq = tmp_path / "seq"
    make_demo_sequence(seq, n_frames=6, seed=1, size=(160, 120), config=SyntheticConfig(laps=2))
    np.save(seq / "gt.npy", np.zeros((6, 6), bool))
    code = BLOCKER + textwrap.dedent(
        f"""
        from aefabmap.cli.main import main
        sys.exit(main(['eval', '--model', r'{bundle}', '--images', r'{seq}', '--gt', r'{seq / "gt.npy"}',
                       '--exclude', '2', '--plot', r'{tmp_path / "pr.png"}', '--no-progress']))
        """
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=100)
    assert proc.returncode == 2
    assert "matplotlib" in proc.stderr
