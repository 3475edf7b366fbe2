"""The README's headline is reproducible: the same training command gives the same bundle bytes."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from aefabmap.cli.main import main


def _files(bundle: Path) -> dict[str, bytes]:
    return {str(p.relative_to(bundle)): p.read_bytes() for p in sorted(bundle.rglob("*")) if p.is_file()}


@pytest.mark.data
@pytest.mark.slow
def test_same_command_from_empty_caches_gives_identical_bytes(train_images, tmp_path):
    """40 CamVid frames, 64 words, trained twice, each from its own empty feature cache, then
    once more from the first (now warm) cache: every file of the three bundles is identical."""
    images = tmp_path / "images"
    images.mkdir()
    for p in train_images[::17][:40]:
        shutil.copy(p, images / p.name)

    def train(out: str, cache: str) -> Path:
        args = ["train", "--images", str(images), "--features", "orb", "--quantizer", "kmeans", "--words", "64",
                "--seed", "0", "--out", str(tmp_path / out), "--cache", str(tmp_path / cache), "--no-progress"]
        assert main(args) == 0
        return tmp_path / out

    first, second = train("a", "cache_a"), train("b", "cache_b")
    warm = train("c", "cache_a")
    a = _files(first)
    assert "manifest.json" in a and "vocabulary.npy" in a and len(a) >= 7
    assert a == _files(second)
    assert a == _files(warm)
