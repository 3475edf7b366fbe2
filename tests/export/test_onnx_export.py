"""ONNX export of the AE-VQ quantiser: fp32 parity with torch, int8 agreement, determinism."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tests.conftest import train_dir

torch = pytest.importorskip("torch")
onnx = pytest.importorskip("onnx")

from aefabmap_export.onnx_export import QuantizerGraph, export_quantizer_onnx  # noqa: E402
from aefabmap_export.quantize_int8 import quantize_int8  # noqa: E402
from aefabmap_runtime.core.words.onnx_quantizer import OnnxQuantizer  # noqa: E402
from aefabmap_trainer.ae_quantizer import build_ae_quantizer, descriptor_sample  # noqa: E402
from aefabmap_trainer.autoencoder import AeConfig, train_autoencoder  # noqa: E402
from aefabmap_trainer.latent_vocabulary import fit_latent_vocabulary  # noqa: E402

WORDS = 64
# Three short epochs keep the fixture fast. A barely trained encoder gives codes with small
# Voronoi margins, the hard case for int8: it must still agree with fp32 on >= 99 % of words.
TINY = AeConfig(max_epochs=3, max_descriptors=3000, batch_size=64, threads=1, progress=False)
CONFIGS = {"paper": TINY, "light": AeConfig(arch="light", **{k: v for k, v in TINY.__dict__.items() if k != "arch"})}


class Exported:
    """A tiny trained quantiser of one feature kind, its files and held-out test vectors."""

    def __init__(self, kind: str, out: Path, arch: str = "paper") -> None:
        d = train_dir()
        train_paths = sorted((d / "camvid").glob("*.jpg"))[:15]
        # Held-out images from another dataset: parity must not depend on training data.
        test_paths = sorted((d / "scene15" / "street").glob("*.jpg"))[:12]
        self.kind = kind
        self.train = descriptor_sample(train_paths, kind, limit=3000)
        self.test = descriptor_sample(test_paths, kind, limit=2000)
        res = train_autoencoder(self.train, feature_kind=kind, seed=0, config=CONFIGS[arch])
        self.encoder = res.model.encoder
        self.codebook = fit_latent_vocabulary(self.encoder, self.train, WORDS, seed=0, max_iterations=10).codebook
        self.fp32 = export_quantizer_onnx(self.encoder, self.codebook, out / f"{kind}_fp32.onnx")
        self.int8 = quantize_int8(self.fp32, out / f"{kind}_int8.onnx", self.train)
        self.d = self.train.shape[1]

    def runtime(self, which: str = "fp32") -> OnnxQuantizer:
        return OnnxQuantizer(getattr(self, which), vocabulary_size=WORDS, descriptor_length=self.d)

    def eager(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Torch words, codes and latent scores (N, K) for x."""
        g = QuantizerGraph(self.encoder, self.codebook).eval()
        with torch.no_grad():
            words, codes = g(torch.from_numpy(x))
            scores = g.scores(codes)
        return words.numpy(), codes.numpy(), scores.numpy()


def tie_gap(scores: np.ndarray, words_a: np.ndarray, words_b: np.ndarray) -> np.ndarray:
    """Where two quantisers' words differ: |score of a's word - score of b's word| over the row's
    score scale (largest |score| + 1), from latent scores (N, K); a (0,) array when they agree."""
    rows = np.flatnonzero(words_a != words_b)
    gap = np.abs(scores[rows, words_a[rows]] - scores[rows, words_b[rows]])
    return gap / (np.abs(scores[rows]).max(axis=1) + 1.0)


@pytest.fixture(scope="module", params=["orb", "sift", "orb-light", "sift-light"])
def exported(request, tmp_path_factory) -> Exported:
    kind, _, arch = request.param.partition("-")
    return Exported(kind, tmp_path_factory.mktemp(f"ae_{request.param}"), arch or "paper")


pytestmark = pytest.mark.slow  # ~10-20 s per feature kind for the shared fixture


def test_graph_contract_and_checker(exported):
    model = onnx.load(str(exported.fp32))
    onnx.checker.check_model(model, full_check=True)
    assert [i.name for i in model.graph.input] == ["descriptors"]
    assert [o.name for o in model.graph.output] == ["words", "codes"]
    dims = model.graph.input[0].type.tensor_type.shape.dim
    assert dims[0].dim_param and dims[1].dim_value == exported.d
    assert model.graph.output[0].type.tensor_type.elem_type == onnx.TensorProto.INT32
    meta = {p.key: p.value for p in model.metadata_props}
    assert meta["vocabulary_size"] == str(WORDS)
    onnx.checker.check_model(onnx.load(str(exported.int8)))
    int8_ops = {n.op_type for n in onnx.load(str(exported.int8)).graph.node}
    assert "QuantizeLinear" in int8_ops and "DequantizeLinear" in int8_ops
    assert "ConvInteger" not in int8_ops and "MatMulInteger" not in int8_ops  # static QDQ, not dynamic


def test_fp32_onnx_matches_torch_eager(exported):
    x = exported.test
    words_t, codes_t, scores = exported.eager(x)
    words_o, codes_o = exported.runtime().quantize_and_encode(x)
    np.testing.assert_allclose(codes_o, codes_t, rtol=1e-4, atol=1e-4)
    differ = np.flatnonzero(words_o != words_t)
    # Two float32 GEMM implementations can only disagree on a genuine tie: the two words'
    # latent scores must then be equal to float precision.
    assert np.all(tie_gap(scores, words_o, words_t) <= 1e-4), f"{differ.size} non-tie disagreements"
    assert differ.size <= max(1, x.shape[0] // 1000)


def test_int8_agrees_with_fp32(exported):
    # Integer kernels differ by CPU (AVX2 pair sums, AVX-512 VNNI dot products), and with them
    # which near-tie int8 rounding tips: on this barely trained encoder agreement was >= 99 % on
    # the project's AVX2 machines and 98.95-99.45 % on an AVX-512 VNNI one. What must hold on
    # every CPU: int8 picks another word only where fp32's two words are near a tie, within two
    # int8 steps (2/127) of the score scale (weights and activations are both rounded, each by up
    # to half a step of its own scale, so one step is no bound), and such ties are rare. (Trained
    # bundles are measured against the 99 % target in docs/results.md.)
    w32 = exported.runtime("fp32").quantize(exported.test)
    w8 = exported.runtime("int8").quantize(exported.test)
    agreement = float(np.mean(w32 == w8))
    assert agreement >= 0.98, f"int8 agrees on {agreement:.4f} of descriptors"
    _, _, scores = exported.eager(exported.test)
    gap = tie_gap(scores, w32, w8)
    assert np.all(gap <= 2.0 / 127), f"int8 changed words with an fp32 margin of up to {gap.max():.4f} of the scale"


def test_int8_weights_cannot_saturate_int16_pair_sums(exported):
    # u8 activations (<= 255) times s8 weights, summed in pairs in int16 by onnxruntime's
    # non-VNNI x86 kernels: |w| <= 64 keeps 2 * 255 * |w| <= 32767 (export/aefabmap_export/quantize_int8.py).
    from onnx import numpy_helper

    model = onnx.load(str(exported.int8))
    weights = [numpy_helper.to_array(t) for t in model.graph.initializer if t.data_type == onnx.TensorProto.INT8]
    assert weights, "no int8 weights in the int8 graph"
    assert max(int(np.abs(w.astype(np.int32)).max()) for w in weights) <= 64


def test_int8_kernels_compute_the_graphs_qdq_arithmetic(exported):
    # Fused integer kernels (all optimisations) vs the same graph run as float Q/DQ ops (none):
    # equal up to requantisation rounding. Saturating 8-bit weights made them differ by 11 %
    # (ORB) on this project's AVX2 machines.
    import onnxruntime as ort

    def codes(level):
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = 1
        opts.graph_optimization_level = level
        s = ort.InferenceSession(str(exported.int8), opts, providers=["CPUExecutionProvider"])
        return s.run(["codes"], {"descriptors": exported.test})[0]

    fused = codes(ort.GraphOptimizationLevel.ORT_ENABLE_ALL)
    emulated = codes(ort.GraphOptimizationLevel.ORT_DISABLE_ALL)
    assert np.linalg.norm(fused - emulated) <= 1e-3 * np.linalg.norm(emulated)


def test_graph_arg_max_is_the_first_maximum_across_blocks_and_padding(tmp_path):
    # The graph's arg-max runs in blocks of argmax_block(K) scores, with the codebook padded to
    # whole blocks: it must still give the first index of the row's maximum, as one flat
    # arg-max does, wherever ties fall (inside a block, across a block boundary, in the padded
    # last block) and never a padding index. K = 70 -> blocks of 16, 80 columns.
    from aefabmap_export.onnx_export import argmax_block
    from aefabmap_trainer.autoencoder import Autoencoder

    torch.manual_seed(0)
    words = 70
    assert argmax_block(words) == 16 and words % 16
    enc = Autoencoder(128, AeConfig(arch="light", latent_dim=8).resolved(128, "sift")).encoder.eval()
    rng = np.random.default_rng(1)
    x = rng.random((400, 128)).astype(np.float32)
    with torch.no_grad():
        codes = enc(torch.from_numpy(x)).numpy()
    codebook = (codes[rng.choice(400, words, replace=False)] + rng.normal(0, 0.5, (words, 8))).astype(np.float32)
    # Codewords equal to the codes of rows 0-2, each duplicated further on: exact score ties.
    pairs = [(3, 9), (15, 16), (64, 69)]
    for row, (first, second) in enumerate(pairs):
        codebook[first] = codebook[second] = codes[row]
    model = OnnxQuantizer(export_quantizer_onnx(enc, codebook, tmp_path / "q.onnx"), vocabulary_size=words,
                          descriptor_length=128)
    got = model.quantize(x)
    assert got.max() < words
    assert got[: len(pairs)].tolist() == [first for first, _ in pairs]
    scores = model.encode(x) @ codebook.T - 0.5 * np.einsum("kd,kd->k", codebook, codebook)
    flat = np.argmax(scores, axis=1)
    # Duplicated codewords tie exactly in the graph but may differ in the last bit of numpy's
    # float32 product (which BLAS kernel runs depends on the CPU): the reference is the first
    # index within rounding of the row's maximum, not numpy's arg-max.
    scale = np.abs(scores).max(axis=1, keepdims=True) + 1.0
    first = np.argmax(scores >= scores.max(axis=1, keepdims=True) - 1e-6 * scale, axis=1)
    assert np.all(tie_gap(scores, got, flat) <= 1e-5) and np.mean(got == first) >= 0.99


@pytest.mark.parametrize("which", ["fp32", "int8"])
def test_batched_equals_one_by_one(exported, which):
    q = exported.runtime(which)
    x = exported.test[:300]
    batched = q.quantize(x)
    single = np.concatenate([q.quantize(x[i : i + 1]) for i in range(x.shape[0])])
    assert np.array_equal(batched, single)
    codes = q.encode(x)
    codes1 = np.concatenate([q.encode(x[i : i + 1]) for i in range(x.shape[0])])
    np.testing.assert_allclose(codes, codes1, rtol=1e-5, atol=1e-5)


def test_build_ae_quantizer_is_deterministic(tmp_path):
    d = train_dir()
    vectors = descriptor_sample(sorted((d / "camvid").glob("*.jpg"))[:6], "orb", limit=2000)
    cfg = AeConfig(max_epochs=1, max_descriptors=1500, batch_size=128, threads=1, progress=False)
    manifests = []
    for name in ("a", "b"):
        manifests.append(
            build_ae_quantizer(vectors, words=16, seed=5, feature_kind="orb", out_dir=tmp_path / name, config=cfg)
        )
    m = manifests[0]
    assert m["type"] == "ae" and m["files"] == {"fp32": "quantizer_fp32.onnx", "int8": "quantizer_int8.onnx"}
    assert m["latent_dim"] == 128 and 0.0 <= m["int8_agreement"] <= 1.0
    assert m["train"]["n_descriptors"] == 1500
    for f in m["files"].values():
        assert (tmp_path / "a" / f).read_bytes() == (tmp_path / "b" / f).read_bytes(), f
    import json

    json.dumps(m)  # JSON-able
