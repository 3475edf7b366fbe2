"""runtime/aefabmap_runtime/core/words/onnx_quantizer.py: validation, edge cases, and no torch/onnx at run time.

The model files are made with the trainer (torch); a runtime-only install skips these tests.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from aefabmap_runtime.errors import BundleError, ConfigError, InputError
from aefabmap_runtime.core.words.onnx_quantizer import OnnxQuantizer

REPO = Path(__file__).resolve().parents[4]
WORDS = 16


@pytest.fixture(scope="module")
def model(tmp_path_factory) -> Path:
    """An untrained-but-valid SIFT quantiser graph (random weights, random codebook)."""
    torch = pytest.importorskip("torch")
    pytest.importorskip("onnx")
    from aefabmap_export.onnx_export import export_quantizer_onnx
    from aefabmap_trainer.autoencoder import AeConfig, Autoencoder

    torch.manual_seed(0)
    cfg = AeConfig().resolved(128, "sift")
    enc = Autoencoder(128, cfg).encoder.eval()
    codebook = np.random.default_rng(0).normal(size=(WORDS, cfg.latent_dim)).astype(np.float32) * 0.1
    return export_quantizer_onnx(enc, codebook, tmp_path_factory.mktemp("oq") / "q.onnx")


def _vectors(n: int, seed: int = 1) -> np.ndarray:
    x = np.random.default_rng(seed).random((n, 128)).astype(np.float32)
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def test_quantize_and_encode(model):
    q = OnnxQuantizer(model, vocabulary_size=WORDS, descriptor_length=128, threads=1)
    assert (q.vocabulary_size, q.descriptor_length, q.latent_dim) == (WORDS, 128, 64)
    words = q.quantize(_vectors(50))
    assert words.dtype == np.int32 and words.shape == (50,)
    assert words.min() >= 0 and words.max() < WORDS
    codes = q.encode(_vectors(50))
    assert codes.dtype == np.float32 and codes.shape == (50, 64)
    w2, c2 = q.quantize_and_encode(_vectors(50))
    assert np.array_equal(w2, words) and np.array_equal(c2, codes)


def test_empty_input(model):
    q = OnnxQuantizer(model, vocabulary_size=WORDS, descriptor_length=128)
    assert q.quantize(np.zeros((0, 128), np.float32)).shape == (0,)
    assert q.quantize(np.zeros((0, 128), np.float32)).dtype == np.int32
    assert q.encode(np.zeros((0, 128), np.float32)).shape == (0, 64)


def test_bad_input_raises_input_error(model):
    q = OnnxQuantizer(model, vocabulary_size=WORDS, descriptor_length=128)
    with pytest.raises(InputError):
        q.quantize(np.zeros((3, 256), np.float32))
    with pytest.raises(InputError):
        q.quantize(np.zeros(128, np.float32))
    bad = _vectors(2)
    bad[0, 0] = np.inf
    with pytest.raises(InputError):
        q.quantize(bad)


def test_float64_input_is_accepted(model):
    q = OnnxQuantizer(model, vocabulary_size=WORDS, descriptor_length=128)
    x = _vectors(10)
    assert np.array_equal(q.quantize(x.astype(np.float64)), q.quantize(x))


@pytest.mark.parametrize(
    "kwargs,match",
    [({"vocabulary_size": WORDS + 1, "descriptor_length": 128}, "codebook of 16 words"),
     ({"vocabulary_size": WORDS, "descriptor_length": 256}, "length 128")],
)
def test_shape_mismatch_raises_bundle_error(model, kwargs, match):
    with pytest.raises(BundleError, match=match):
        OnnxQuantizer(model, **kwargs)


def test_missing_and_corrupt_files(tmp_path):
    with pytest.raises(BundleError, match="does not exist"):
        OnnxQuantizer(tmp_path / "nope.onnx", vocabulary_size=WORDS, descriptor_length=128)
    bad = tmp_path / "corrupt.onnx"
    bad.write_bytes(b"this is not a protobuf" * 10)
    with pytest.raises(BundleError, match="cannot load"):
        OnnxQuantizer(bad, vocabulary_size=WORDS, descriptor_length=128)


def test_truncated_model_raises_bundle_error(model, tmp_path):
    data = model.read_bytes()
    cut = tmp_path / "cut.onnx"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(BundleError):
        OnnxQuantizer(cut, vocabulary_size=WORDS, descriptor_length=128)


def test_foreign_graph_raises_bundle_error(tmp_path):
    onnx = pytest.importorskip("onnx")
    from onnx import TensorProto, helper

    x = helper.make_tensor_value_info("x", TensorProto.FLOAT, ["n", 128])
    y = helper.make_tensor_value_info("y", TensorProto.FLOAT, ["n", 128])
    graph = helper.make_graph([helper.make_node("Identity", ["x"], ["y"])], "g", [x], [y])
    path = tmp_path / "identity.onnx"
    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)], ir_version=8), str(path))
    with pytest.raises(BundleError, match="expected one input 'descriptors'"):
        OnnxQuantizer(path, vocabulary_size=WORDS, descriptor_length=128)


def test_bad_arguments_raise_config_error(model):
    with pytest.raises(ConfigError):
        OnnxQuantizer(model, vocabulary_size=WORDS, descriptor_length=128, threads=0)


def test_runtime_path_imports_neither_torch_nor_onnx(model):
    code = textwrap.dedent(
        f"""
        import sys
        import numpy as np
        from aefabmap_runtime.core.words.onnx_quantizer import OnnxQuantizer
        q = OnnxQuantizer({str(model)!r}, vocabulary_size={WORDS}, descriptor_length=128, threads=1)
        x = np.random.default_rng(0).random((20, 128)).astype(np.float32)
        w = q.quantize(x)
        assert w.shape == (20,) and w.dtype == np.int32
        assert 'torch' not in sys.modules, 'torch was imported'
        assert 'onnx' not in sys.modules, 'onnx was imported'
        print('ok')
        """
    )
    env = {k: v for k, v in os.environ.items() if k != "PYTHONSTARTUP"}
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, env=env, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip().endswith("ok")


def _hostile_model(path: Path, offset: int) -> Path:
    """A valid-looking quantiser graph whose word ids are ``round(sum(x)) + offset``."""
    onnx = pytest.importorskip("onnx")
    from onnx import TensorProto, helper

    graph = helper.make_graph(
        [
            helper.make_node("ReduceSum", ["descriptors", "axes"], ["s"], keepdims=0),
            helper.make_node("Cast", ["s"], ["si"], to=TensorProto.INT64),
            helper.make_node("Add", ["si", "offset"], ["words"]),
            helper.make_node("Identity", ["descriptors"], ["codes"]),
        ],
        "hostile",
        [helper.make_tensor_value_info("descriptors", TensorProto.FLOAT, ["batch", 128])],
        [
            helper.make_tensor_value_info("words", TensorProto.INT64, ["batch"]),
            helper.make_tensor_value_info("codes", TensorProto.FLOAT, ["batch", 128]),
        ],
        initializer=[
            helper.make_tensor("axes", TensorProto.INT64, [1], [1]),
            helper.make_tensor("offset", TensorProto.INT64, [], [offset]),
        ],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    helper.set_model_props(model, {"vocabulary_size": str(WORDS)})
    onnx.save(model, path)
    return path


@pytest.mark.parametrize("offset", [-100, 100])
def test_word_ids_outside_the_vocabulary_are_a_bundle_error(tmp_path, offset, monkeypatch):
    path = _hostile_model(tmp_path / "h.onnx", offset)
    with pytest.raises(BundleError, match="outside"):  # refused at load by the probe
        OnnxQuantizer(path, vocabulary_size=WORDS, descriptor_length=128)
    # and, should a model pass the probe, on every call
    monkeypatch.setattr(OnnxQuantizer, "_probe", lambda self: None)
    q = OnnxQuantizer(path, vocabulary_size=WORDS, descriptor_length=128)
    with pytest.raises(BundleError, match="outside"):
        q.quantize(_vectors(5))
    with pytest.raises(BundleError, match="outside"):
        q.quantize_and_encode(_vectors(5))
    assert q.quantize(np.zeros((0, 128), np.float32)).shape == (0,)


def _with_full_range_weights(int8_path: Path, out: Path) -> Path:
    """The same QDQ graph with int8 weights doubled and their scales halved (bias likewise).

    The float arithmetic the graph describes is unchanged, but weights now reach +-127: the
    range that saturates int16 pair sums in u8 x s8 kernels on x86 without VNNI. This is
    what export/aefabmap_export/quantize_int8.py wrote before it switched to 7-bit weights.
    """
    onnx = pytest.importorskip("onnx")
    from onnx import numpy_helper

    model = onnx.load(str(int8_path))
    init = {t.name: t for t in model.graph.initializer}
    for node in model.graph.node:
        if node.op_type != "DequantizeLinear" or node.input[0] not in init:
            continue
        q, scale = init[node.input[0]], init[node.input[1]]
        if q.data_type not in (onnx.TensorProto.INT8, onnx.TensorProto.INT32):
            continue
        values = numpy_helper.to_array(q).astype(np.int64) * 2
        if q.data_type == onnx.TensorProto.INT8:
            values = np.clip(values, -127, 127)
        q.CopyFrom(numpy_helper.from_array(values.astype(numpy_helper.to_array(q).dtype), q.name))
        s = numpy_helper.to_array(scale)
        scale.CopyFrom(numpy_helper.from_array((s / 2).astype(s.dtype), scale.name))
    out.write_bytes(model.SerializeToString())
    return out


def test_int8_graph_runs_its_qdq_arithmetic_even_with_full_range_weights(model, tmp_path):
    ort = pytest.importorskip("onnxruntime")
    from aefabmap_export.quantize_int8 import quantize_int8

    # 0/1 rows pass the min-max scaling unchanged and quantise to 0/255: the worst case.
    bits = np.random.default_rng(2).integers(0, 2, (400, 128)).astype(np.float32)
    int8 = _with_full_range_weights(quantize_int8(model, tmp_path / "q8.onnx", bits), tmp_path / "q8_full.onnx")
    opts = ort.SessionOptions()
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_DISABLE_ALL  # Q/DQ as float ops
    emulated = ort.InferenceSession(str(int8), opts, providers=["CPUExecutionProvider"]).run(
        ["codes"], {"descriptors": bits})[0]
    fused = OnnxQuantizer(int8, vocabulary_size=WORDS, descriptor_length=128, threads=1).encode(bits)
    # Saturating kernels were off by > 1 % here (on AVX2 without VNNI); rounding alone is ~1e-4.
    assert np.linalg.norm(fused - emulated) <= 1e-3 * np.linalg.norm(emulated)


@pytest.mark.parametrize("where", ["inside", "outside"])
def test_a_model_whose_weights_live_in_an_external_file_is_refused_without_reading_it(model, tmp_path, where):
    """External data (onnx's own format) is never loaded: inside the bundle it is not covered by
    the manifest's checksums; outside it is a read outside the bundle. Nothing of it is opened."""
    onnx = pytest.importorskip("onnx")
    from onnx.external_data_helper import convert_model_to_external_data

    bundle = tmp_path / "bundle"
    bundle.mkdir()
    proto = onnx.load(str(model))
    convert_model_to_external_data(proto, all_tensors_to_one_file=True, location="weights.bin", size_threshold=0)
    onnx.save_model(proto, str(bundle / "q.onnx"))
    weights = bundle / "weights.bin"
    weights.write_bytes(b"\0" * weights.stat().st_size)  # zeroed weights: the tampering
    if where == "outside":  # onnx refuses to write such a location; a hostile bundle need not ask it
        weights.rename(tmp_path / "outside_weights.bin")
        for t in proto.graph.initializer:
            for entry in t.external_data:
                if entry.key == "location":
                    entry.value = "../outside_weights.bin"
        (bundle / "q.onnx").write_bytes(proto.SerializeToString())
    with pytest.raises(BundleError, match="external data"):
        OnnxQuantizer(bundle / "q.onnx", vocabulary_size=WORDS, descriptor_length=128)


def test_external_data_scan_finds_tensors_in_attributes_and_refuses_malformed_bytes(model):
    onnx = pytest.importorskip("onnx")
    from onnx import helper, numpy_helper

    from aefabmap_runtime.core.words.onnx_external import has_external_data

    assert not has_external_data(model.read_bytes())
    tensor = numpy_helper.from_array(np.ones(4, np.float32), "c")
    tensor.data_location = onnx.TensorProto.EXTERNAL
    node = helper.make_node("Constant", [], ["y"], value=tensor)
    graph = helper.make_graph([node], "g", [], [helper.make_tensor_value_info("y", onnx.TensorProto.FLOAT, [4])])
    assert has_external_data(helper.make_model(graph).SerializeToString())
    for bad in (b"\xff", b"\x0a\x05ab", b"\x0f"):
        with pytest.raises(BundleError):
            has_external_data(bad)
