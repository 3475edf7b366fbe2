"""The AE-VQ autoencoder and its latent vocabulary (trainer side: needs torch)."""

from __future__ import annotations

import numpy as np
import pytest

from tests.conftest import train_dir

torch = pytest.importorskip("torch")

from aefabmap_runtime.errors import ConfigError, InputError  # noqa: E402
from aefabmap_trainer.ae_quantizer import descriptor_sample  # noqa: E402
from aefabmap_trainer.autoencoder import (  # noqa: E402
    AeConfig,
    Autoencoder,
    RowScale,
    encode,
    train_autoencoder,
)
from aefabmap_trainer.latent_vocabulary import fit_latent_vocabulary  # noqa: E402


@pytest.fixture(scope="module")
def sift_vectors() -> np.ndarray:
    paths = sorted((train_dir() / "camvid").glob("*.jpg"))[:12]
    return descriptor_sample(paths, "sift", limit=2500)


@pytest.fixture(scope="module")
def orb_vectors() -> np.ndarray:
    paths = sorted((train_dir() / "camvid").glob("*.jpg"))[:12]
    return descriptor_sample(paths, "orb", limit=2500)


TINY = AeConfig(max_epochs=1, max_descriptors=2000, batch_size=128, threads=1, progress=False)


def test_config_defaults_resolve_per_kind():
    orb = AeConfig().resolved(256, "orb")
    sift = AeConfig().resolved(128, "sift")
    assert (orb.latent_dim, orb.scaling) == (128, "none")
    assert (sift.latent_dim, sift.scaling) == (64, "minmax")


@pytest.mark.parametrize(
    "kwargs",
    [{"latent_dim": 0}, {"widths": ()}, {"scaling": "zscore"}, {"max_epochs": 0}, {"val_fraction": 0.9},
     {"learning_rate": 0.0}, {"threads": 0}],
)
def test_bad_config_raises_config_error(kwargs):
    with pytest.raises(ConfigError):
        AeConfig(**kwargs)


def test_descriptor_length_must_fit_pooling():
    with pytest.raises(ConfigError):
        AeConfig(widths=(8, 8, 8, 8, 8, 8, 8, 8)).resolved(128, "sift")
    with pytest.raises(ConfigError):
        AeConfig().resolved(128, "surf")


def test_row_scale_minmax_and_constant_rows():
    x = torch.tensor([[0.2, 0.4, 0.6], [1.0, 1.0, 1.0]])
    y = RowScale("minmax")(x)
    assert torch.allclose(y[0], torch.tensor([0.0, 0.5, 1.0]))
    assert torch.equal(y[1], torch.zeros(3))  # no NaN for a constant row
    assert torch.equal(RowScale("none")(x), x)


@pytest.mark.parametrize("d,kind", [(256, "orb"), (128, "sift")])
def test_shapes(d, kind):
    cfg = AeConfig().resolved(d, kind)
    model = Autoencoder(d, cfg).eval()
    x = torch.rand(5, d)
    with torch.no_grad():
        assert model.encoder(x).shape == (5, cfg.latent_dim)
        assert model(x).shape == (5, d)


@pytest.mark.slow
def test_training_reduces_loss_and_is_deterministic(sift_vectors):
    a = train_autoencoder(sift_vectors, feature_kind="sift", seed=3, config=TINY)
    b = train_autoencoder(sift_vectors, feature_kind="sift", seed=3, config=TINY)
    # BCE of a constant 0.5 prediction is ln 2 = 0.693; one epoch must beat that clearly.
    assert a.best_val_loss < 0.6
    assert a.n_train + a.n_val == 2000
    sa, sb = a.model.state_dict(), b.model.state_dict()
    assert all(torch.equal(sa[k], sb[k]) for k in sa)
    summary = a.summary()
    assert summary["epochs"] == 1 and summary["n_descriptors"] == 2000


@pytest.mark.slow
def test_orb_training_and_latent_vocabulary(orb_vectors):
    res = train_autoencoder(orb_vectors, feature_kind="orb", seed=0, config=TINY)
    assert res.best_val_loss < 0.69
    vocab = fit_latent_vocabulary(res.model.encoder, orb_vectors, 32, seed=0, max_iterations=5)
    assert vocab.codebook.shape == (32, 128) and vocab.codebook.dtype == np.float32
    words = vocab.assign(encode(res.model.encoder, orb_vectors))
    assert words.dtype == np.int32 and words.min() >= 0 and words.max() < 32
    again = fit_latent_vocabulary(res.model.encoder, orb_vectors, 32, seed=0, max_iterations=5)
    assert np.array_equal(vocab.codebook, again.codebook)


def test_bad_training_input():
    with pytest.raises(InputError):
        train_autoencoder(np.zeros((5, 128), np.float32), feature_kind="sift", config=TINY)
    bad = np.zeros((100, 128), np.float32)
    bad[0, 0] = np.nan
    with pytest.raises(InputError):
        train_autoencoder(bad, feature_kind="sift", config=TINY)


LIGHT = AeConfig(arch="light", max_epochs=2, max_descriptors=2000, batch_size=128, threads=1, progress=False)


def test_light_arch_resolves_and_has_the_same_interface():
    cfg = AeConfig(arch="light").resolved(256, "orb")
    assert cfg.widths == (256,) and cfg.latent_dim == 32
    model = Autoencoder(256, cfg).eval()
    with torch.no_grad():
        assert model.encoder(torch.rand(3, 256)).shape == (3, 32)
        assert model(torch.rand(3, 256)).shape == (3, 256)
    with pytest.raises(ConfigError):
        AeConfig(arch="resnet")


def test_light_ae_trains_quickly_on_tiny_data(orb_vectors):
    res = train_autoencoder(orb_vectors, feature_kind="orb", seed=0, config=LIGHT)
    assert res.best_val_loss < 0.69  # better than a constant 0.5 prediction
    assert [h["epoch"] for h in res.history] == [1, 2]
    assert res.summary()["history"][0]["val_recon"] > 0


def test_early_stopping_stops_on_a_flat_held_out_loss(orb_vectors):
    # min_delta larger than any possible gain: only epoch 1 counts as an improvement, so with
    # patience 1 the run stops after epoch 3 of 50 and keeps epoch 1's weights.
    cfg = AeConfig(arch="light", max_epochs=50, max_descriptors=2000, patience=1, min_delta=10.0,
                   threads=1, progress=False)
    res = train_autoencoder(orb_vectors, feature_kind="orb", seed=0, config=cfg)
    assert (res.epochs_run, res.best_epoch, res.stop_reason) == (3, 1, "patience")


def test_time_budget_ends_training(orb_vectors):
    cfg = AeConfig(arch="light", max_epochs=50, max_descriptors=2000, max_seconds=1e-6, threads=1, progress=False)
    res = train_autoencoder(orb_vectors, feature_kind="orb", seed=0, config=cfg)
    assert res.stop_reason == "budget" and res.epochs_run == 0


def test_matching_term_pulls_pairs_together(orb_vectors):
    # Synthetic pairs: a descriptor and a copy with 8 of its 256 bits flipped (a near-duplicate).
    rng = np.random.default_rng(0)
    a = orb_vectors[:1200]
    b = a.copy()
    flip = rng.random(b.shape).argsort(axis=1)[:, :8]
    np.put_along_axis(b, flip, 1.0 - np.take_along_axis(b, flip, axis=1), axis=1)
    tr, va = (a[:1000], b[:1000]), (a[1000:], b[1000:])
    plain = train_autoencoder(orb_vectors, feature_kind="orb", seed=0, config=LIGHT, pairs=tr, val_pairs=va)
    cfg = AeConfig(**{**LIGHT.__dict__, "match_weight": 1.0})
    matched = train_autoencoder(orb_vectors, feature_kind="orb", seed=0, config=cfg, pairs=tr, val_pairs=va)
    # The held-out matching loss is reported for both; training on it must lower it.
    assert matched.history[-1]["val_match"] < plain.history[-1]["val_match"]
    assert matched.summary()["loss"] == "bce+match"
    with pytest.raises(InputError):
        train_autoencoder(orb_vectors, feature_kind="orb", config=cfg)  # no pairs


def test_image_negatives_need_groups_and_train(orb_vectors):
    a, b = orb_vectors[:1000], orb_vectors[:1000].copy()
    cfg = AeConfig(**{**LIGHT.__dict__, "max_epochs": 1, "match_weight": 0.1, "match_negatives": "image"})
    with pytest.raises(InputError):
        train_autoencoder(orb_vectors, feature_kind="orb", config=cfg, pairs=(a[:800], b[:800]), val_pairs=(a[800:], b[800:]))
    res = train_autoencoder(orb_vectors, feature_kind="orb", config=cfg, pairs=(a[:800], b[:800]),
                            val_pairs=(a[800:], b[800:]), pair_groups=np.repeat(np.arange(8), 100))
    assert res.history[0]["val_match"] is not None
