"""`aefabmap bench quantizer`: JSON keys and variants for flat, tree and AE bundles."""

from __future__ import annotations

import json

import pytest

from aefabmap.cli.main import main
from aefabmap_runtime.errors import ConfigError
from aefabmap_runtime.tools.quantizer_bench import resolve_variant
from tests.conftest import make_synthetic_tree_bundle

KEYS = {"ms_per_500_median", "ms_per_500_p95", "variant", "feature_kind", "words", "bundle_id", "descriptors"}


def _bench(tmp_path, *args) -> dict:
    out = tmp_path / "bq.json"
    assert main(["bench", "quantizer", *args, "--repeats", "3", "--json", str(out)]) == 0
    return json.loads(out.read_text())


def test_shipped_bundle_is_kmeans_flat(tmp_path):
    doc = _bench(tmp_path)
    assert KEYS <= set(doc) and doc["variant"] == "kmeans-flat" and doc["feature_kind"] == "orb"
    assert doc["words"] == 500 and doc["descriptors"] == 500 and doc["ms_per_500_median"] > 0
    assert doc["single_core"] and doc["threads_env"]["OMP_NUM_THREADS"] == "1"


def test_tree_bundle_is_kmeans_tree(tmp_path):
    bundle = make_synthetic_tree_bundle(tmp_path / "tree")
    doc = _bench(tmp_path, "--model", str(bundle), "--variant", "kmeans-tree", "--all-cores")
    assert doc["variant"] == "kmeans-tree" and doc["words"] == 40 and doc["tree"]["distance"] == "hamming"


def test_variant_that_the_bundle_does_not_have_is_refused(tmp_path):
    assert main(["bench", "quantizer", "--variant", "kmeans-tree", "--repeats", "1", "--all-cores"]) == 2
    assert resolve_variant({"type": "ae"}, None) == "ae-fp32" and resolve_variant({"type": "ae"}, "int8") == "ae-int8"
    indexed = {"type": "kmeans", "index": {}}
    assert resolve_variant(indexed, None) == "kmeans-indexed" and resolve_variant(indexed, "kmeans-flat") == "kmeans-flat"
    with pytest.raises(ConfigError):
        resolve_variant({"type": "ae"}, "kmeans-flat")
    with pytest.raises(ConfigError):
        resolve_variant({"type": "kmeans"}, "kmeans-indexed")


@pytest.mark.slow
def test_ae_bundle_fp32_and_int8(tmp_path):
    pytest.importorskip("torch")
    pytest.importorskip("onnx")
    from aefabmap_runtime.core.features.features import FeatureConfig
    from aefabmap_runtime.tools.synthetic_route import SyntheticConfig, make_demo_sequence
    from aefabmap_trainer.train import TrainConfig, train_bundle

    images = tmp_path / "imgs"
    make_demo_sequence(images, n_frames=8, seed=7, size=(320, 240), config=SyntheticConfig(laps=1))
    res = train_bundle(TrainConfig(images=(images,), out=tmp_path / "ae", features=FeatureConfig("orb", 200),
                                   quantizer="ae", ae_objective="recon", words=16, max_descriptors=1000, ae_epochs=1,
                                   ae_descriptors=1000, show_progress=False))
    fp32 = _bench(tmp_path, "--model", str(res.path), "--all-cores")
    int8 = _bench(tmp_path, "--model", str(res.path), "--variant", "int8", "--all-cores")
    assert (fp32["variant"], int8["variant"]) == ("ae-fp32", "ae-int8")
    assert fp32["bundle_id"] == int8["bundle_id"] and int8["ms_per_500_median"] > 0
