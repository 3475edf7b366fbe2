"""Fixtures of the trainer's tests."""

from __future__ import annotations

import pytest

from aefabmap_runtime.tools.synthetic_route import SyntheticConfig, make_demo_sequence


@pytest.fixture(scope="module")
def image_dir(tmp_path_factory):
    """16 generated frames of the demo route (no ground truth file): a small training set."""
    d = tmp_path_factory.mktemp("imgs")
    make_demo_sequence(d, n_frames=16, seed=7, size=(320, 240), config=SyntheticConfig(laps=1))
    (d / "gt.npy").unlink()
    return d
