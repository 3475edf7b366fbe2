"""The int8 flat search of bit vectors: exactly the words of the float64 arg-min, ties included."""

from __future__ import annotations

import numpy as np
import onnxruntime as ort
import pytest

from aefabmap_runtime.errors import InputError
from aefabmap_runtime.core.words.bit_centroids import BLOCK_BYTES, BitCentroidQuantizer, product_chunk
from aefabmap_runtime.core.words.onnx_matmul import INPUT_NAME, OUTPUT_NAME, matmul_integer_model
from aefabmap_runtime.core.words.quantizer import NearestCentroidQuantizer


def _exact_words(bits: np.ndarray, centroids: np.ndarray) -> np.ndarray:
    """Reference: float64 arg-min of squared L2 (|x|^2 - 2 x.c + |c|^2), the lowest id on a tie."""
    c = centroids.astype(np.float64)
    return np.argmin((c * c).sum(axis=1) - 2.0 * bits.astype(np.float64) @ c.T, axis=1)


def _clustered(seed: int, k: int = 300, n: int = 2000, d: int = 256):
    """Mean-of-bits centroids of k noisy clusters (as k-means leaves them) and descriptors drawn
    near them, so that many descriptors sit between two close centroids."""
    rng = np.random.default_rng(seed)
    prototypes = rng.random((k // 3, d)) < 0.5
    members = prototypes[rng.integers(0, k // 3, (k, 40))] ^ (rng.random((k, 40, d)) < 0.2)
    centroids = members.mean(axis=1).astype(np.float32)
    bits = (prototypes[rng.integers(0, k // 3, n)] ^ (rng.random((n, d)) < 0.25)).astype(np.uint8)
    return centroids, bits


def test_the_written_graph_multiplies_exactly_at_the_int8_extremes():
    """onnxruntime's int8 product of the hand-written graph equals int32 arithmetic, with every
    weight at +-127 and every bit set (the case that would saturate int16 pair sums of 8-bit
    operands), and the bytes are a valid ONNX model where the onnx package is installed."""
    rng = np.random.default_rng(0)
    weights = rng.choice(np.array([-127, 127, 0, 5], np.int8), size=(256, 77))
    bits = rng.integers(0, 2, (40, 256), dtype=np.uint8)
    bits[0] = 1
    weights[:, 0] = 127
    weights[:, 1] = -127
    model = matmul_integer_model(weights)
    session = ort.InferenceSession(model, providers=["CPUExecutionProvider"])
    got = session.run([OUTPUT_NAME], {INPUT_NAME: bits})[0]
    assert got.dtype == np.int32
    assert np.array_equal(got, bits.astype(np.int32) @ weights.astype(np.int32))
    assert got[0, 0] == 256 * 127 and got[0, 1] == -256 * 127
    onnx = pytest.importorskip("onnx")
    onnx.checker.check_model(onnx.load_from_string(model), full_check=True)


@pytest.mark.parametrize("seed", [1, 2])
def test_words_equal_the_exact_arg_min(seed, kernels):
    centroids, bits = _clustered(seed)
    q = BitCentroidQuantizer(centroids, chunk=700)  # several chunks, the last one short
    packed = q.quantize_raw(np.packbits(bits, axis=1))
    unpacked = q.quantize(bits.astype(np.float32))
    expect = _exact_words(bits, centroids)
    assert packed.dtype == np.int32 and np.array_equal(packed, expect) and np.array_equal(unpacked, expect)
    # The float32 product agrees except where two scores tie within its rounding (these centroids
    # are multiples of 1/40, so exact ties occur; float32 then need not pick the lowest id).
    assert (NearestCentroidQuantizer(centroids).quantize(bits.astype(np.float32)) == expect).mean() > 0.99


def test_ties_go_to_the_lowest_id_and_far_centroids_stay_exact(kernels):
    """Duplicate centroids tie exactly (the lowest id wins, as np.argmin); centroids outside
    [0, 1] are clipped in int8 but the band widens with them, so the words stay exact."""
    centroids, bits = _clustered(3, k=60, n=500)
    centroids = np.concatenate([centroids, centroids[::-1]])  # every centroid twice
    wild = centroids.copy()
    wild[::7] = wild[::7] * 3.0 - 1.0
    words = BitCentroidQuantizer(centroids).quantize_raw(np.packbits(bits, axis=1))
    wild_words = BitCentroidQuantizer(wild).quantize_raw(np.packbits(bits, axis=1))
    assert np.array_equal(words, _exact_words(bits, centroids)) and words.max() < 60
    assert np.array_equal(wild_words, _exact_words(bits, wild))


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_words_stay_exact_when_every_residual_has_one_sign(sign, kernels):
    """Each word's interval of the int8 error is one-sided when every centroid value lies above
    (or below) its int8 level, by up to half a step, by different amounts in each word: the
    candidates must still hold the exact best word."""
    centroids, bits = _clustered(7, k=200, n=1500)
    levels = np.clip(np.rint(127 * (2.0 * centroids.astype(np.float64) - 1.0)), -126, 126)
    offsets = np.random.default_rng(7).random(levels.shape) * np.linspace(0.0, 0.99, levels.shape[0])[:, None]
    snapped = ((levels / 127 + 1.0) / 2 + sign * offsets / 508).astype(np.float32)
    q = BitCentroidQuantizer(snapped)
    assert np.array_equal(q.quantize_raw(np.packbits(bits, axis=1)), _exact_words(bits, snapped))


def test_product_chunks_keep_the_block_of_products_in_cache():
    for words in (1, 300, 1000, 2000, 3000, 5000, 10**5):
        chunk = product_chunk(words)
        assert 64 <= chunk <= 512 and chunk & (chunk - 1) == 0
        assert chunk * words * 4 <= BLOCK_BYTES or chunk == 64
        assert chunk == 512 or 2 * chunk * words * 4 > BLOCK_BYTES  # the largest that fits
    centroids, bits = _clustered(8, k=300, n=1300)
    packed = np.packbits(bits, axis=1)
    assert np.array_equal(BitCentroidQuantizer(centroids).quantize_raw(packed),
                          BitCentroidQuantizer(centroids, chunk=100).quantize_raw(packed))


def test_vectors_that_are_not_bits_take_the_float_search():
    centroids, _ = _clustered(6, k=30, n=10)
    x = np.random.default_rng(6).random((50, 256)).astype(np.float32)
    x[0] = 2.0
    expect = NearestCentroidQuantizer(centroids).quantize(x)
    assert np.array_equal(BitCentroidQuantizer(centroids).quantize(x), expect)


def test_empty_input_and_hostile_arrays_are_input_errors():
    centroids, _ = _clustered(4, k=30, n=10)
    q = BitCentroidQuantizer(centroids)
    assert q.quantize_raw(np.zeros((0, 32), np.uint8)).shape == (0,)
    bad_inputs = [
        (q.quantize_raw, np.zeros((3, 31), np.uint8)),  # wrong width
        (q.quantize_raw, np.zeros((3, 32), np.int16)),  # not bytes
        (q.quantize, np.zeros((3, 255), np.float32)),
    ]
    for call, bad in bad_inputs:
        with pytest.raises(InputError):
            call(bad)
    for bad_centroids in (np.full((4, 256), np.nan, np.float32), np.zeros((4, 250), np.float32),
                          np.zeros((0, 256), np.float32)):
        with pytest.raises(InputError):
            BitCentroidQuantizer(bad_centroids)
