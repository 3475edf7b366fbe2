"""The word-assignment objective (--ae-objective assign) and its multi-view tracks, on generated data."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from aefabmap_runtime.errors import ConfigError, InputError  # noqa: E402
from aefabmap_runtime.core.features.features import FeatureConfig, FeatureExtractor  # noqa: E402
from aefabmap_trainer.assign_objective import (  # noqa: E402
    AssignConfig,
    assign_loss,
    balance_loss,
    consistency_loss,
    init_linear_pca,
    log_assign,
    train_assign,
)
from aefabmap_trainer.autoencoder import AeConfig  # noqa: E402
from aefabmap_trainer.multiview import Tracks, build_tracks, darken, is_test_image  # noqa: E402
from tests.trainer.test_match_pairs import textured_image  # noqa: E402


def bit_data(seed: int = 0, prototypes: int = 24, n: int = 1200, tracks: int = 320, views: int = 4,
             flips: int = 12, nuisance: int = 160) -> tuple[np.ndarray, Tracks]:
    """ORB-like 0/1 vectors (n, 256) around random prototypes, and tracks (tracks, views, 256):
    one prototype per track, each view with `flips` random bits flipped and its first `nuisance`
    bits drawn afresh (they change between views, as unstable tests of a descriptor do; a
    vocabulary of the raw bits splits views by them); views 3+ sometimes missing."""
    rng = np.random.default_rng(seed)
    proto = rng.integers(0, 2, (prototypes, 256)).astype(np.float32)

    def noisy(p: np.ndarray) -> np.ndarray:
        x = p.copy()
        idx = rng.integers(0, 256, (x.shape[0], flips))
        np.put_along_axis(x, idx, 1.0 - np.take_along_axis(x, idx, 1), 1)
        x[:, :nuisance] = rng.integers(0, 2, (x.shape[0], nuisance))
        return x

    vectors = noisy(proto[rng.integers(0, prototypes, n)])
    who = rng.integers(0, prototypes, tracks)
    x = np.stack([noisy(proto[who]) for _ in range(views)], axis=1)
    mask = np.ones((tracks, views), bool)
    mask[:, 3:] = rng.random((tracks, views - 3)) < 0.7
    return vectors, Tracks(x, mask, (np.arange(tracks) // 8).astype(np.int32))


TINY = AeConfig(arch="light", widths=(32,), latent_dim=8, max_epochs=8, max_descriptors=1200, threads=1,
                progress=False)
TINY_ASSIGN = AssignConfig(anneal_epochs=2, track_batch=32, descriptor_batch=64, restart_sample=400,
                           init_kmeans_iterations=3)


def test_consistency_is_lower_when_views_share_a_word():
    codebook = torch.eye(4) * 3.0  # 4 words, far apart
    same = torch.stack([codebook[[0, 1]]] * 3, dim=1)  # (2 tracks, 3 views, 4): every view on its track's word
    split = torch.stack([codebook[[0, 1]], codebook[[2, 3]], codebook[[0, 1]]], dim=1)
    mask = torch.ones(2, 3, dtype=torch.bool)

    def loss(z):
        return float(consistency_loss(log_assign(z.reshape(6, 4), codebook, 0.2, 9.0).view(2, 3, 4), mask))

    assert loss(same) < 0.1 < 1.0 < loss(split)
    # a masked-out view does not count: the split track's odd view hidden -> consistent again
    mask[:, 1] = False
    assert float(consistency_loss(log_assign(split.reshape(6, 4), codebook, 0.2, 9.0).view(2, 3, 4), mask)) < 0.1


def test_balance_is_zero_for_even_use_and_log_k_for_one_word():
    assert float(balance_loss(torch.full((8,), 1 / 8))) == pytest.approx(0.0, abs=1e-6)
    assert float(balance_loss(torch.tensor([1.0] + [0.0] * 7))) == pytest.approx(math.log(8), abs=1e-6)
    # one word for everything is perfectly consistent, but the total loss is higher than with
    # consistent tracks spread over the words
    codebook = torch.eye(4) * 3.0
    mask = torch.ones(4, 3, dtype=torch.bool)
    one = torch.stack([codebook[[0, 0, 0, 0]]] * 3, dim=1).reshape(12, 4)
    spread = torch.stack([codebook[[0, 1, 2, 3]]] * 3, dim=1).reshape(12, 4)
    total = [float(assign_loss(log_assign(z, codebook, 0.5, 9.0).view(4, 3, 4), mask, None, 1.0)[0]) for z in (one, spread)]
    assert total[1] < total[0]


def test_temperature_anneals_geometrically_then_stays():
    c = AssignConfig(temperature_start=1.0, temperature_end=0.01, anneal_epochs=2)
    assert [c.temperature(e) for e in (1, 2, 3, 9)] == pytest.approx([1.0, 0.1, 0.01, 0.01])
    with pytest.raises(ConfigError):
        AssignConfig(temperature_end=0.0)


def test_training_raises_held_out_agreement_and_is_byte_identical():
    vectors, tracks = bit_data()
    train, val = tracks.split(0.25, 0)
    runs = [train_assign(vectors, train, val, words=16, feature_kind="orb", seed=3, config=TINY, assign=TINY_ASSIGN)
            for _ in range(2)]
    a, b = runs
    assert a.codebook.shape == (16, 8) and a.codebook.dtype == np.float32
    assert a.codebook.tobytes() == b.codebook.tobytes()
    sa, sb = a.model.state_dict(), b.model.state_dict()
    assert all(sa[k].numpy().tobytes() == sb[k].numpy().tobytes() for k in sa)
    assert [h["epoch"] for h in a.history] == list(range(9)) and a.epochs_run == 8
    assert a.history[-1]["val_agreement"] > a.history[0]["val_agreement"]
    s = a.summary()
    assert s["objective"] == "assign" and s["n_tracks_val"] == len(val) and s["assign"]["anneal_epochs"] == 2


def test_kmeans_start_is_a_linear_projection_and_k_means_of_it():
    """init "kmeans": the light encoder computes exactly P (x - mean) through its ReLU layer (P the
    top principal axes), the codes share one scale (distances only rescaled), and the first words
    are k-means of those codes: the vocabulary starts as a k-means vocabulary of the descriptors."""
    from aefabmap_trainer.assign_objective import start_vocabulary
    from aefabmap_trainer.autoencoder import Autoencoder
    from aefabmap_trainer.kmeans import KMeansConfig, fit_kmeans

    vectors, _ = bit_data()
    x = torch.from_numpy(vectors)
    cfg = AeConfig(arch="light", widths=(20,), latent_dim=8, threads=1).resolved(256, "orb")
    model = Autoencoder(256, cfg)
    start = AssignConfig(init="kmeans", init_kmeans_iterations=25)
    words = start_vocabulary(model, x, x[:400], 16, start, seed=3)

    xd = x.double()
    _, vecs = torch.linalg.eigh(torch.cov(xd.T, correction=0))
    p = vecs[:, -8:].flip(1).T
    p = p * torch.where(p.sum(1, keepdim=True) < 0, -1.0, 1.0)
    projected = (xd - xd.mean(0)) @ p.T
    codes = projected / math.sqrt(float(projected.var(0, unbiased=False).mean()) + 1e-5)
    model.encoder.eval()
    with torch.no_grad():
        assert torch.allclose(model.encoder(x).double(), codes, atol=1e-4)
    assert not model.encoder.per_dimension
    expected = fit_kmeans(codes.float().numpy(), 16, KMeansConfig(max_iterations=25, seed=3))
    assert np.allclose(words.numpy(), expected, atol=1e-3)
    with pytest.raises(ConfigError):  # a hidden layer narrower than 2 L cannot carry +P and -P
        init_linear_pca(Autoencoder(256, AeConfig(arch="light", widths=(12,), latent_dim=8).resolved(256, "orb")).encoder, x)
    with pytest.raises(ConfigError):
        AssignConfig(init="pca")


def test_kmeans_start_trains_and_is_byte_identical():
    vectors, tracks = bit_data()
    train, val = tracks.split(0.25, 0)
    start = AssignConfig(**{**TINY_ASSIGN.to_dict(), "init": "kmeans"})
    cfg = AeConfig(**{**TINY.to_dict(), "widths": (16,), "max_epochs": 4})
    a, b = (train_assign(vectors, train, val, words=16, feature_kind="orb", seed=3, config=cfg, assign=start)
            for _ in range(2))
    assert a.codebook.tobytes() == b.codebook.tobytes() and a.codebook.shape == (16, 8)
    assert min(h["val_loss"] for h in a.history) == a.best_val_loss


def test_reconstruction_term_counts_at_every_epoch_the_initial_one_included():
    # Early stopping compares epochs: epoch 0 (the start) must be scored by the same sum.
    vectors, tracks = bit_data()
    train, val = tracks.split(0.25, 0)
    run = train_assign(vectors, train, val, words=16, feature_kind="orb", seed=3,
                       config=AeConfig(**{**TINY.to_dict(), "max_epochs": 2}),
                       assign=AssignConfig(**{**TINY_ASSIGN.to_dict(), "recon_weight": 0.5}))
    for h in run.history:
        assert h["val_recon"] is not None
        assert h["val_loss"] == pytest.approx(h["val_consistency"] + h["val_balance"] + 0.5 * h["val_recon"])


def test_bad_inputs_raise():
    vectors, tracks = bit_data(tracks=40)
    two_views = Tracks(tracks.x[:, :2], tracks.mask[:, :2], tracks.group)
    with pytest.raises(InputError):
        train_assign(vectors, two_views, tracks, words=16, feature_kind="orb", config=TINY, assign=TINY_ASSIGN)
    with pytest.raises(ConfigError):
        train_assign(vectors, tracks, tracks, words=5000, feature_kind="orb", config=TINY, assign=TINY_ASSIGN)


@pytest.mark.parametrize("settings", [
    dict(ae_arch="paper"),  # the paper's conv stack cannot take the (default) objective
    dict(ae_objective="assign", ae_arch="light", ae_views=2),
    dict(ae_objective="assign", ae_arch="light", ae_views=4, ae_light_views=4),
    dict(ae_objective="assign", ae_arch="light", ae_light_views=-1),
    dict(ae_objective="other"),
    dict(ae_objective="recon", ae_init="kmeans"),  # a start for the assign objective only
    dict(ae_objective="assign", ae_arch="light", ae_init="pca"),
    dict(ae_temperature_end=0.0),
    dict(ae_temperature_end=float("nan")),
    dict(ae_temperature_end=float("inf")),
])
def test_train_config_refuses_bad_assign_settings(settings, tmp_path):
    from aefabmap_trainer.train import TrainConfig

    with pytest.raises(ConfigError):
        TrainConfig(images=(tmp_path,), out=tmp_path / "b", quantizer="ae", **settings)


def test_assign_bundle_exports_the_trained_codebook(tmp_path, monkeypatch):
    """The ONNX graph's words are the trained codebook's arg-min over the trained encoder's codes."""
    import aefabmap_export.onnx_export as onnx_export
    from aefabmap_runtime.core.words.onnx_quantizer import OnnxQuantizer
    from aefabmap_trainer.ae_quantizer import build_ae_quantizer
    from aefabmap_trainer.assign_objective import squared_distances

    exported = {}
    real = onnx_export.export_quantizer_onnx

    def spy(encoder, codebook, path):
        exported.update(encoder=encoder, codebook=codebook)
        return real(encoder, codebook, path)

    monkeypatch.setattr(onnx_export, "export_quantizer_onnx", spy)
    vectors, tracks = bit_data()
    entry = build_ae_quantizer(vectors, words=16, seed=0, feature_kind="orb", out_dir=tmp_path, config=TINY,
                               objective="assign", tracks=tracks, assign=TINY_ASSIGN)
    assert entry["vocabulary"]["codebook"] == "trained" and "kmeans" not in entry
    assert entry["train"]["objective"] == "assign"
    q = OnnxQuantizer(tmp_path / entry["files"]["fp32"], vocabulary_size=16, descriptor_length=256, threads=1)
    x = vectors[:200]
    with torch.no_grad():
        expected = squared_distances(exported["encoder"](torch.from_numpy(x)), torch.from_numpy(exported["codebook"])).argmin(1)
    assert np.mean(q.quantize(x) == expected.numpy()) > 0.99
    assert entry["int8_agreement"] > 0.5


def test_tracks_need_three_views_and_keep_the_test_split_out(tmp_path):
    rng = np.random.default_rng(0)
    img = textured_image(0)
    night = darken(img, rng, gain=0.3, gamma=2.2, noise=4.0, blur=0.8)
    assert night.dtype == np.uint8 and night.mean() < img.mean()
    names = [f"img_{i:03d}.png" for i in range(40)]
    files = [tmp_path / n for n in names if not is_test_image(Path(n))][:3] + [tmp_path / n for n in names if is_test_image(Path(n))][:1]
    fx = FeatureExtractor(FeatureConfig(kind="orb", long_side=None))
    loaded = []

    def load(p):
        loaded.append(p)
        return textured_image(names.index(p.name))

    t = build_tracks(files, fx, images=10, views=4, seed=0, load=load)
    assert t.x.shape[1:] == (4, 256) and t.mask.shape == t.x.shape[:2] and len(t) > 20
    assert t.mask[:, 0].all() and (t.mask.sum(1) >= 3).all()
    assert not any(is_test_image(p) for p in loaded) and len(set(loaded)) == 3
    assert set(np.unique(t.group)) <= {0, 1, 2}
    with pytest.raises(InputError):
        build_tracks(files, fx, images=2, views=4, min_views=2, seed=0, load=load)


def test_light_views_are_the_unwarped_image_at_night(tmp_path):
    """The last light_views copies keep the image's geometry: nearly every keypoint of the image is
    found again there, and their descriptors are nearer to the image's than a warped view's are."""
    names = [f"img_{i:03d}.png" for i in range(40)]
    files = [tmp_path / n for n in names if not is_test_image(Path(n))][:3]
    fx = FeatureExtractor(FeatureConfig(kind="orb", long_side=None, contrast_stretch=True))

    def load(p):
        return textured_image(names.index(p.name))

    plain = build_tracks(files, fx, images=3, views=4, seed=0, load=load)
    same = build_tracks(files, fx, images=3, views=4, seed=0, light_views=0, load=load)
    assert np.array_equal(plain.x, same.x) and np.array_equal(plain.mask, same.mask)
    t = build_tracks(files, fx, images=3, views=4, seed=0, light_views=1, load=load)
    assert len(t) > 20
    bits = lambda a, b: np.abs(a - b).sum(-1)  # noqa: E731 - Hamming distance of 0/1 vectors
    light = bits(t.x[t.mask[:, 3], 0], t.x[t.mask[:, 3], 3])
    warped = bits(t.x[t.mask[:, 1], 0], t.x[t.mask[:, 1], 1])
    assert t.mask[:, 3].mean() > t.mask[:, 1].mean() and np.median(light) < np.median(warped)
    with pytest.raises(InputError):
        build_tracks(files, fx, images=3, views=4, seed=0, light_views=4, load=load)


def test_test_pairs_come_from_the_test_split_only(tmp_path):
    from aefabmap_trainer.multiview import build_test_pairs

    names = [f"img_{i:03d}.png" for i in range(60)]
    files = [tmp_path / n for n in names]
    loaded = []

    def load(p):
        loaded.append(p)
        return textured_image(names.index(p.name))

    pairs = build_test_pairs(files, FeatureExtractor(FeatureConfig(kind="orb", long_side=None)), images=2, seed=0,
                             load=load)
    assert set(pairs) == {"viewpoint", "night", "viewpoint+night"}
    assert all(len(p) > 10 and p.a.shape == p.b.shape == (len(p), 256) for p in pairs.values())
    assert loaded and all(is_test_image(p) for p in loaded) and len(set(loaded)) == 2
    # the night copy keeps the geometry: most of its pairs are the same keypoint, few bits apart
    night = pairs["night"]
    assert np.median(np.abs(night.a - night.b).sum(1)) < 64
