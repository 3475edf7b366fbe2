"""kmeans-tree bundles: round trip through the writer and reader, hostile manifests and arrays refused."""

from __future__ import annotations

import json

import numpy as np
import pytest

from aefabmap_runtime.errors import BundleError
from aefabmap_runtime.adapters.bundle_reader import load_bundle, load_detector, sha256_file
from aefabmap_runtime.core.words.vocab_tree import VocabularyTree
from tests.conftest import make_synthetic_tree_bundle

CENTERS, CHILDREN, WORDS = "vocab_tree_centers.npy", "vocab_tree_children.npy", "vocab_tree_leaf_words.npy"


@pytest.fixture
def tree_bundle(tmp_path):
    return make_synthetic_tree_bundle(tmp_path / "tree")


def _manifest(bundle) -> dict:
    return json.loads((bundle / "manifest.json").read_text())


def _edit_quantizer(bundle, **entries) -> None:
    m = _manifest(bundle)
    m["quantizer"].update(entries)
    (bundle / "manifest.json").write_text(json.dumps(m))


def _replace_array(bundle, name: str, array: np.ndarray) -> None:
    np.save(bundle / name, array, allow_pickle=False)
    m = _manifest(bundle)
    m["files"][name] = sha256_file(bundle / name)
    (bundle / "manifest.json").write_text(json.dumps(m))


@pytest.mark.parametrize("kind", ["orb", "sift"])
def test_round_trip_gives_the_same_words(tmp_path, kind):
    bundle = load_bundle(make_synthetic_tree_bundle(tmp_path / kind, kind=kind))
    q = bundle.quantizer()
    assert isinstance(q, VocabularyTree) and q.vocabulary_size == bundle.vocabulary_size == 40
    assert q.accepts_packed_bits == (kind == "orb")
    rng = np.random.default_rng(0)
    kind_spec = bundle.features.spec
    raw = rng.integers(0, 256, (100, 32), dtype=np.uint8) if kind == "orb" else kind_spec.finish(rng.random((100, 128)))
    again = VocabularyTree(np.load(bundle.path / CENTERS), np.load(bundle.path / CHILDREN), np.load(bundle.path / WORDS))
    words = q.quantize(kind_spec.vectors(raw))
    assert np.array_equal(words, again.quantize(kind_spec.vectors(raw))) and words.max() < 40


def test_detector_runs_a_tree_bundle_on_an_image(tree_bundle):
    det = load_detector(tree_bundle)
    img = (np.random.default_rng(1).random((240, 320)) * 255).astype(np.uint8)
    res = det.process(img)
    assert res.n_keypoints > 0 and "quantise" in res.timings_ms


@pytest.mark.parametrize(
    "entries, message",
    [
        ({"nodes": 10**9}, "'nodes' must be an integer"),
        ({"nodes": "51"}, "'nodes' must be an integer"),
        ({"nodes": 2}, "'nodes' must be an integer"),
        ({"branching": 1}, "'branching' must be an integer"),
        ({"branching": 10**6}, "'branching' must be an integer"),
        ({"branching": True}, "'branching' must be an integer"),
        ({"distance": "cosine"}, "'distance' must be"),
        ({"files": {"centers": CENTERS, "children": CHILDREN}}, "names the files"),
    ],
)
def test_hostile_manifest_entries_are_refused(tree_bundle, entries, message):
    _edit_quantizer(tree_bundle, **entries)
    with pytest.raises(BundleError, match=message):
        load_bundle(tree_bundle).quantizer()


def test_node_count_that_disagrees_with_the_array_headers_is_refused_before_loading(tree_bundle):
    m = _manifest(tree_bundle)["quantizer"]["nodes"]
    _edit_quantizer(tree_bundle, nodes=m - 1)
    with pytest.raises(BundleError, match="has shape"):
        load_bundle(tree_bundle).quantizer()


def test_hamming_centres_on_a_float_kind_are_refused(tmp_path):
    bundle = make_synthetic_tree_bundle(tmp_path / "sift", kind="sift")
    _edit_quantizer(bundle, distance="hamming")
    with pytest.raises(BundleError, match="binary feature kind"):
        load_bundle(bundle).quantizer()


def test_hostile_arrays_are_refused(tree_bundle):
    children = np.load(tree_bundle / CHILDREN)
    words = np.load(tree_bundle / WORDS)
    centers = np.load(tree_bundle / CENTERS)
    cases = [
        (CHILDREN, np.where(children == children.max(), 0, children), "invalid vocabulary tree"),  # a cycle
        (CHILDREN, children.astype(np.float32), "dtype"),
        (WORDS, np.where(words == 0, 99, words).astype(np.int32), "invalid vocabulary tree"),
        (CENTERS, centers.astype(np.uint16), "must hold uint8"),
        (CENTERS, centers[:, :16].copy(), "has shape"),
    ]
    for name, array, message in cases:
        original = np.load(tree_bundle / name)
        _replace_array(tree_bundle, name, array)
        with pytest.raises(BundleError, match=message):
            load_bundle(tree_bundle).quantizer()
        _replace_array(tree_bundle, name, original)
    load_bundle(tree_bundle).quantizer()  # restored: valid again


def test_leaf_count_must_match_the_vocabulary_size(tree_bundle):
    m = _manifest(tree_bundle)
    m["vocabulary_size"] = 39
    (tree_bundle / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(BundleError):
        load_bundle(tree_bundle).quantizer()


def test_lying_header_is_refused_before_allocation(tree_bundle):
    path = tree_bundle / CHILDREN
    data = path.read_bytes()
    m = _manifest(tree_bundle)["quantizer"]
    header_shape = f"({m['nodes']}, {m['branching']})".encode()
    assert header_shape in data
    # Claim 10^9 rows in the header while the manifest says `nodes`: the shape check refuses first.
    big = data.replace(header_shape, f"(1000000000, {m['branching']})".encode())
    path.write_bytes(big)
    mm = _manifest(tree_bundle)
    mm["files"][CHILDREN] = sha256_file(path)
    (tree_bundle / "manifest.json").write_text(json.dumps(mm))
    with pytest.raises(BundleError, match="has shape"):
        load_bundle(tree_bundle).quantizer()


@pytest.fixture(scope="module")
def indexed_bundle(tmp_path_factory):
    """A synthetic flat bundle plus an index built on generated vectors."""
    from aefabmap_export.bundle_writer import write_bundle
    from aefabmap_runtime.core.features.features import FeatureConfig
    from aefabmap_runtime.core.words.quantizer import NearestCentroidQuantizer
    from aefabmap_runtime.tools.synthetic_observations import random_tree, synthetic_observations
    from aefabmap_trainer.centroid_index import build_lists, fit_routing
    from aefabmap_trainer.kmeans import KMeansConfig
    from aefabmap_trainer.train import INDEX_FILE_NAMES

    rng = np.random.default_rng(0)
    centroids = rng.random((64, 256)).astype(np.float32)
    x = (rng.random((3000, 256)) < 0.5).astype(np.float32)
    centers = fit_routing(x, 4, binary=True, config=KMeansConfig(4))
    indptr, words = build_lists(centers, centroids, [(x, NearestCentroidQuantizer(centroids).quantize(x))])
    files = {"centroids": "vocabulary.npy", **INDEX_FILE_NAMES}
    return write_bundle(
        tmp_path_factory.mktemp("idx") / "bundle", features=FeatureConfig("orb", 200), tree=random_tree(64, 0),
        training_observations=synthetic_observations(20, 64, 10, 0),
        quantizer={"type": "kmeans", "files": files,
                   "index": {"buckets": 4, "entries": int(words.size), "distance": "hamming"}},
        quantizer_files={"vocabulary.npy": centroids, INDEX_FILE_NAMES["index_centers"]: centers,
                         INDEX_FILE_NAMES["index_indptr"]: indptr, INDEX_FILE_NAMES["index_words"]: words},
        training_summary={"synthetic": True},
    )


def test_indexed_bundle_round_trip(indexed_bundle):
    b = load_bundle(indexed_bundle)
    q, flat = b.quantizer(), b.quantizer("flat")
    assert type(q).__name__ == "IndexedCentroidQuantizer" and q.buckets == 4
    raw = np.random.default_rng(1).integers(0, 256, (50, 32), dtype=np.uint8)
    w = q.quantize_raw(raw)
    assert w.shape == (50,) and w.max() < 64 and flat.quantize(b.features.spec.vectors(raw)).max() < 64


@pytest.mark.parametrize(
    "index, message",
    [
        ({"buckets": 10**9}, "'buckets' must be an integer"),
        ({"entries": 10**12}, "'entries' must be an integer"),
        ({"entries": 3}, "'entries' must be an integer"),
        ({"distance": "l1"}, "'distance' must be"),
        ({"distance": "l2"}, "has dtype uint8"),
        ({"buckets": 5}, "has shape"),
    ],
)
def test_hostile_index_entries_are_refused(indexed_bundle, tmp_path, index, message):
    import shutil

    bundle = tmp_path / "b"
    shutil.copytree(indexed_bundle, bundle)
    m = _manifest(bundle)
    m["quantizer"]["index"].update(index)
    (bundle / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(BundleError, match=message):
        load_bundle(bundle).quantizer()
    load_bundle(bundle).quantizer("flat")  # the exhaustive search never reads the index


def test_hostile_index_arrays_are_refused(indexed_bundle, tmp_path):
    import shutil

    bundle = tmp_path / "b"
    shutil.copytree(indexed_bundle, bundle)
    words = np.load(bundle / "index_words.npy")
    _replace_array(bundle, "index_words.npy", np.where(words == words.max(), 64, words).astype(np.int32))
    with pytest.raises(BundleError, match="invalid vocabulary index"):
        load_bundle(bundle).quantizer()
