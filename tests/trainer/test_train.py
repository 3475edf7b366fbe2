"""Training pipeline on generated images: bundle validity, feature cache, the AE quantiser path."""

from __future__ import annotations

import numpy as np
import pytest

from aefabmap.runtime.adapters.bundle_reader import load_bundle
from aefabmap.runtime.core.features import FeatureConfig
from aefabmap.runtime.tools.synthetic_route import SyntheticConfig, make_demo_sequence
from aefabmap.trainer import train as train_mod
from aefabmap.trainer.train import TrainConfig, train_bundle


@pytest.fixture(scope="module")
def image_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("imgs")
    make_demo_sequence(d, n_frames=16, seed=7, size=(320, 240), config=SyntheticConfig(laps=1))
    (d / "gt.npy").unlink()
    return d


def config(image_dir, out, **kw):
    base = dict(images=(image_dir,), out=out, features=FeatureConfig("orb", 200), words=32, max_descriptors=2000, show_progress=False)
    base.update(kw)
    return TrainConfig(**base)


def test_kmeans_bundle_and_cache(image_dir, tmp_path, monkeypatch):
    cache = tmp_path / "cache"
    first = train_bundle(config(image_dir, tmp_path / "a", cache_dir=cache))
    b = load_bundle(first.path)
    assert b.vocabulary_size == 32 and len(b.training_observations) == 16
    assert len(list(cache.glob("features-orb-*.npz"))) == 1

    def no_extraction(*a, **k):
        raise AssertionError("features were extracted again despite the cache")

    monkeypatch.setattr(train_mod, "extract_training_vectors", no_extraction)
    second = train_bundle(config(image_dir, tmp_path / "b", cache_dir=cache))
    assert load_bundle(second.path).manifest["files"] == b.manifest["files"]
    # Other feature settings must not reuse the entry.
    with pytest.raises(AssertionError, match="extracted again"):
        train_bundle(config(image_dir, tmp_path / "c", cache_dir=cache, features=FeatureConfig("orb", 150)))


@pytest.mark.slow
def test_ae_bundle_quantises_like_its_onnx_graph(image_dir, tmp_path):
    pytest.importorskip("torch")
    pytest.importorskip("onnx")
    # One thread: on a loaded machine two torch threads waiting for each other are ~15x slower.
    res = train_bundle(config(image_dir, tmp_path / "ae", quantizer="ae", ae_threads=1))
    b = load_bundle(res.path)
    assert b.quantizer_type == "ae"
    assert set(b.manifest["quantizer"]["files"]) == {"fp32", "int8"}
    q32, q8 = b.quantizer("fp32"), b.quantizer("int8")
    v = np.random.default_rng(0).integers(0, 2, (300, 256)).astype(np.float32)
    w32, w8 = q32.quantize(v), q8.quantize(v)
    assert w32.shape == (300,) and w32.max() < 32
    # A 3-epoch toy on 16 synthetic frames still agrees on > 99 % (random bits are off its
    # training distribution, hence the margin); int8 kernels saturating int16 gave 0.18.
    assert np.mean(w32 == w8) >= 0.97
    assert b.manifest["quantizer"]["int8_agreement"] >= 0.99  # measured on its training descriptors


@pytest.mark.slow
def test_light_ae_with_matching_term_bundle(image_dir, tmp_path):
    pytest.importorskip("torch")
    pytest.importorskip("onnx")
    cache = tmp_path / "cache"
    cfg = config(image_dir, tmp_path / "light", quantizer="ae", ae_arch="light", ae_match_weight=0.1,
                 ae_warp_images=6, ae_frame_pairs=0, ae_epochs=3, ae_threads=1, cache_dir=cache)
    res = train_bundle(cfg)
    q = load_bundle(res.path).manifest["quantizer"]
    t = q["train"]
    assert t["config"]["arch"] == "light" and q["latent_dim"] == 32 and t["loss"] == "bce+match"
    assert t["n_pairs_train"] > 0 and t["n_pairs_val"] > 0
    assert [h["epoch"] for h in t["history"]] == list(range(1, t["epochs"] + 1))  # the loss curve
    assert 0.0 <= q["pair_word_agreement"]["fp32"] <= 1.0
    assert len(list(cache.glob("pairs-orb-*.npz"))) == 1  # pairs are cached like features
