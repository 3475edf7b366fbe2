"""The README's headline is reproducible: the same training command gives the same bundle bytes."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from aefabmap.cli.main import main


def _files(bundle: Path) -> dict[str, bytes]:
    return {str(p.relative_to(bundle)): p.read_bytes() for p in sorted(bundle.rglob("*")) if p.is_file()}


# The default AE (word-assignment objective), small enough for a test: its manifest keeps a per-epoch history.
AE_ASSIGN = ["--quantizer", "ae", "--ae-epochs", "2", "--ae-descriptors", "4000", "--ae-track-images", "12"]


@pytest.mark.data
@pytest.mark.slow
@pytest.mark.parametrize("quantizer", [["--quantizer", "kmeans"], AE_ASSIGN], ids=["kmeans", "ae-assign"])
def test_same_command_from_empty_caches_gives_identical_bytes(train_images, tmp_path, quantizer):
    """40 CamVid frames, 64 words, trained twice, each from its own empty feature cache, then
    once more from the first (now warm) cache with progress bars on: every file of the three
    bundles is identical."""
    if quantizer[1] == "ae":
        pytest.importorskip("torch")
    images = tmp_path / "images"
    images.mkdir()
    for p in train_images[::17][:40]:
        shutil.copy(p, images / p.name)

    def train(out: str, cache: str, progress: bool = False) -> Path:
        args = ["train", "--images", str(images), "--features", "orb", *quantizer, "--words", "64",
                "--seed", "0", "--out", str(tmp_path / out), "--cache", str(tmp_path / cache)]
        assert main(args if progress else [*args, "--no-progress"]) == 0
        return tmp_path / out

    first, second = train("a", "cache_a"), train("b", "cache_b")
    warm = train("c", "cache_a", progress=True)
    a = _files(first)
    assert "manifest.json" in a and len(a) >= 7
    assert ("quantizer_int8.onnx" if quantizer[1] == "ae" else "vocabulary.npy") in a
    assert a == _files(second)
    assert a == _files(warm)
    training = json.loads(a["manifest.json"])["training"]
    if quantizer[1] == "ae":  # the views the words were trained on are part of the bundle's record
        assert (training["ae_views"], training["ae_light_views"], training["ae_track_images"]) == (6, 0, 12)
    else:
        assert "ae_views" not in training
