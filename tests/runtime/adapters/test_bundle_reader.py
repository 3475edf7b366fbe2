"""Model bundle v1: round trip and refusal of wrong versions, shapes and checksums."""

from __future__ import annotations

import json

import numpy as np
import pytest

from aefabmap import BundleError
from aefabmap_runtime.adapters.bundle_reader import load_bundle, sha256_file
from tests.conftest import make_synthetic_bundle


def test_round_trip(synthetic_bundle):
    b = load_bundle(synthetic_bundle)
    assert b.vocabulary_size == 64 and b.descriptor_length == 256
    assert b.features.kind == "orb"
    assert len(b.training_observations) == 20
    q = b.quantizer()
    words = q.quantize(np.random.default_rng(0).random((5, 256)).astype(np.float32))
    assert words.shape == (5,) and words.max() < 64


def test_same_inputs_same_bytes(tmp_path):
    a = make_synthetic_bundle(tmp_path / "a")
    b = make_synthetic_bundle(tmp_path / "b")
    for f in sorted(p.name for p in a.iterdir()):
        assert sha256_file(a / f) == sha256_file(b / f), f


def _edit_manifest(path, **changes):
    m = json.loads((path / "manifest.json").read_text())
    m.update(changes)
    (path / "manifest.json").write_text(json.dumps(m))


def test_missing_bundle(tmp_path):
    with pytest.raises(BundleError, match="does not exist"):
        load_bundle(tmp_path / "nope")


def test_wrong_version(synthetic_bundle):
    _edit_manifest(synthetic_bundle, format_version=99)
    with pytest.raises(BundleError, match="version 99"):
        load_bundle(synthetic_bundle)


def test_corrupt_file_fails_checksum(synthetic_bundle):
    f = synthetic_bundle / "tree_p.npy"
    data = bytearray(f.read_bytes())
    data[-1] ^= 0xFF
    f.write_bytes(bytes(data))
    with pytest.raises(BundleError, match="checksum mismatch for tree_p.npy"):
        load_bundle(synthetic_bundle)


def test_missing_file(synthetic_bundle):
    (synthetic_bundle / "vocabulary.npy").unlink()
    with pytest.raises(BundleError, match="vocabulary.npy .*missing"):
        load_bundle(synthetic_bundle)


def test_shape_mismatch(synthetic_bundle):
    _edit_manifest(synthetic_bundle, vocabulary_size=65)
    with pytest.raises(BundleError, match="shape"):
        load_bundle(synthetic_bundle)


def test_truncated_manifest(synthetic_bundle):
    m = synthetic_bundle / "manifest.json"
    m.write_text(m.read_text()[:50])
    with pytest.raises(BundleError, match="not JSON"):
        load_bundle(synthetic_bundle)


def test_pickled_array_refused(synthetic_bundle):
    f = synthetic_bundle / "tree_a.npy"
    np.save(f, np.array([{"evil": 1}], dtype=object), allow_pickle=True)
    m = json.loads((synthetic_bundle / "manifest.json").read_text())
    m["files"]["tree_a.npy"] = sha256_file(f)
    (synthetic_bundle / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(BundleError, match="tree_a.npy"):
        load_bundle(synthetic_bundle)


def test_writer_refuses_to_clobber_other_directories(tmp_path):
    d = tmp_path / "precious"
    d.mkdir()
    (d / "notes.txt").write_text("keep me")
    with pytest.raises(BundleError, match="refusing"):
        make_synthetic_bundle(d)
    assert (d / "notes.txt").read_text() == "keep me"


def test_writer_replaces_an_existing_bundle(tmp_path):
    make_synthetic_bundle(tmp_path / "b", seed=0)
    make_synthetic_bundle(tmp_path / "b", seed=1)
    assert load_bundle(tmp_path / "b").training_observations
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b"]


def test_flat_search_of_a_binary_kind_runs_in_int8_with_the_float_words(tmp_path):
    """An ORB k-means bundle searches its flat vocabulary with the int8 product (exact re-rank),
    "flat-fp32" with the float32 product, and the two give the same words; a SIFT bundle keeps
    the float product (its descriptors are not bits)."""
    from aefabmap_runtime.core.words.bit_centroids import BitCentroidQuantizer
    from aefabmap_runtime.core.words.quantizer import NearestCentroidQuantizer, quantize_raw

    b = load_bundle(make_synthetic_bundle(tmp_path / "orb", vocabulary_size=200))
    int8, fp32 = b.quantizer(), b.quantizer("flat-fp32")
    assert isinstance(int8, BitCentroidQuantizer) and isinstance(fp32, NearestCentroidQuantizer)
    raw = np.random.default_rng(5).integers(0, 256, (400, 32), dtype=np.uint8)
    kind = b.features.spec
    assert np.array_equal(quantize_raw(int8, kind, raw), quantize_raw(fp32, kind, raw))
    sift = load_bundle(make_synthetic_bundle(tmp_path / "sift", kind="sift"))
    assert isinstance(sift.quantizer(), NearestCentroidQuantizer)
