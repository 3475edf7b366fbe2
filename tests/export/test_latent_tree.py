"""The two-level latent vocabulary tree: fit, numpy search == ONNX graph search, int8 graph."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")
onnx = pytest.importorskip("onnx")

from aefabmap_export.onnx_export import attach_tree_search, export_quantizer_onnx  # noqa: E402
from aefabmap_export.quantize_int8 import quantize_int8  # noqa: E402
from aefabmap_runtime.core.words.onnx_quantizer import OnnxQuantizer  # noqa: E402
from aefabmap_trainer.autoencoder import AeConfig, Autoencoder, encode  # noqa: E402
from aefabmap_trainer.latent_vocabulary import fit_latent_tree  # noqa: E402


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    rng = np.random.default_rng(0)
    torch.manual_seed(0)
    d = 128
    cfg = AeConfig(arch="light", latent_dim=16).resolved(d, "sift")
    enc = Autoencoder(d, cfg).encoder.eval()
    x = rng.random((3000, d)).astype(np.float32)
    codes = encode(enc, x)
    tree = fit_latent_tree(codes, 100, branches=8, seed=0, max_iterations=10)
    out = tmp_path_factory.mktemp("tree")
    fp32 = export_quantizer_onnx(enc, np.zeros((2, 16), np.float32), out / "flat.onnx")
    int8 = quantize_int8(fp32, out / "flat_int8.onnx", x)
    paths = {}
    for name, p in (("fp32", fp32), ("int8", int8)):
        m = onnx.load(str(p))
        attach_tree_search(m, tree)
        onnx.checker.check_model(m)
        paths[name] = out / f"tree_{name}.onnx"
        paths[name].write_bytes(m.SerializeToString())
    return x, codes, tree, paths


def test_tree_has_k_words_each_leaf_once(setup):
    _, codes, tree, _ = setup
    assert tree.size == 100
    real = tree.leaf_half < 1e29
    assert sorted(tree.ids[real].tolist()) == list(range(100))
    words = tree.assign(codes)
    assert words.min() >= 0 and words.max() < 100 and np.unique(words).size > 80


def test_tree_search_is_the_nearest_leaf_of_the_nearest_cell(setup):
    _, codes, tree, _ = setup
    z = codes[:50]
    ci = np.argmin(((z[:, None] - tree.coarse[None]) ** 2).sum(-1), axis=1)
    for n in range(z.shape[0]):
        real = tree.leaf_half[ci[n]] < 1e29
        dist = ((tree.leaves[ci[n]][real] - z[n]) ** 2).sum(-1)
        assert tree.assign(z[n : n + 1])[0] == tree.ids[ci[n]][real][np.argmin(dist)]


def test_onnx_tree_graph_equals_numpy_search(setup):
    x, codes, tree, paths = setup
    q = OnnxQuantizer(paths["fp32"], vocabulary_size=100, descriptor_length=128)
    assert np.array_equal(q.quantize(x), tree.assign(codes))
    q8 = OnnxQuantizer(paths["int8"], vocabulary_size=100, descriptor_length=128)
    assert np.mean(q8.quantize(x) == q.quantize(x)) > 0.95
