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


#: Every command that needs the `train` extra, with arguments that get it past parsing.
TRAIN_EXTRA_COMMANDS = {
    "train": ["train", "--images", "images", "--out", "bundle"],
    "bench chowliu": ["bench", "chowliu", "--words", "50", "--images", "20", "--words-per-image", "5"],
}


@pytest.mark.slow
@pytest.mark.timeout(900)
@pytest.mark.parametrize("command", sorted(TRAIN_EXTRA_COMMANDS))
def test_commands_of_the_train_extra_name_it_on_a_runtime_install(runtime_install, tmp_path, command):
    """On the real runtime-only install: one line naming aefabmap[train], exit 2 (configuration)."""
    (tmp_path / "images").mkdir()
    proc = runtime_install.run([str(runtime_install.aefabmap), *TRAIN_EXTRA_COMMANDS[command]], cwd=tmp_path)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr, proc.stderr[-2000:]
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "aefabmap[train]" in lines[0], proc.stderr[-2000:]
    assert not (tmp_path / "bundle").exists()


def test_the_train_extra_check_passes_where_the_extra_is_installed(capsys):
    """The counterpart, in this (full) environment: the check lets the command run."""
    from aefabmap.cli.main import main

    assert main(TRAIN_EXTRA_COMMANDS["bench chowliu"]) == 0
    assert '"words": 50' in capsys.readouterr().out
