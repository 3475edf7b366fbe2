"""Shared fixtures: where the real data lives (skipped, not failed, when absent), and the two kernel paths."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def data_root() -> Path:
    """$AEFABMAP_DATA, else shared/data in the directory holding the checkout (docs/data.md)."""
    return Path(os.environ.get("AEFABMAP_DATA", REPO.parent / "shared" / "data"))


def train_dir() -> Path:
    """<data root>/train, or skip the calling test when it is absent."""
    d = data_root() / "train"
    if not d.is_dir():
        pytest.skip(f"training images not found under {data_root()} (set AEFABMAP_DATA)")
    return d


@pytest.fixture(params=["numpy", "native", "numba"])
def kernels(request):
    """Run a test on the numpy / OpenCV fallbacks and on each compiled form of the kernels
    (runtime/aefabmap_runtime/core/kernels/compiled.py; a form that cannot run here is skipped): all must give the same results."""
    from aefabmap_runtime.core.kernels import compiled

    if request.param != "numpy" and request.param not in compiled.backends():
        pytest.skip(f"the {request.param} kernels cannot run here")
    previous = compiled.use(request.param)
    yield request.param
    compiled.use(previous)


@pytest.fixture(params=["native", "numba"])
def on_both_paths(request):
    """run(fn) -> [fn() on the numpy / OpenCV fallbacks, fn() on one compiled form], for tests
    that compare the two paths with each other (once per compiled form; skipped where it cannot run)."""
    from aefabmap_runtime.core.kernels import compiled

    if request.param not in compiled.backends():
        pytest.skip(f"the {request.param} kernels cannot run here")

    def run(fn):
        out = []
        for choice in ("numpy", request.param):
            previous = compiled.use(choice)
            try:
                out.append(fn())
            finally:
                compiled.use(previous)
        return out

    return run


@pytest.fixture(scope="session")
def shared_data() -> Path:
    root = data_root()
    if not (root / "train").is_dir():
        pytest.skip(f"shared data not found at {root} (set AEFABMAP_DATA)")
    return root


@pytest.fixture(scope="session")
def lip6(shared_data) -> Path:
    d = shared_data / "lip6_outdoor"
    if not (d / "ground_truth.npy").is_file():
        pytest.skip("lip6_outdoor not found")
    return d


@pytest.fixture(scope="session")
def train_images(shared_data) -> list[Path]:
    return sorted((shared_data / "train" / "camvid").glob("*.jpg"))


def rectangles_image(seed: int, shape_hw: tuple[int, int] = (240, 320), count: int = 60):
    """(H, W) uint8: `count` filled rectangles (sides 8-39 px, random grey levels) on mid-grey,
    seeded by `seed`: corners for a detector to find."""
    import cv2
    import numpy as np

    rng = np.random.default_rng(seed)
    h, w = shape_hw
    image = np.full((h, w), 128, np.uint8)
    for _ in range(count):
        x, y = rng.integers(0, w - 20), rng.integers(0, h - 20)
        cv2.rectangle(image, (int(x), int(y)), (int(x + rng.integers(8, 40)), int(y + rng.integers(8, 40))),
                      int(rng.integers(0, 256)), -1)
    return image


def make_synthetic_bundle(out: Path, vocabulary_size: int = 64, kind: str = "orb", seed: int = 0) -> Path:
    """A small valid k-means bundle from generated arrays (no training data needed)."""
    import numpy as np

    from aefabmap_export.bundle_writer import write_bundle
    from aefabmap_runtime.core.features.features import FeatureConfig
    from aefabmap_runtime.tools.synthetic_observations import (
        random_tree,
        synthetic_observations,
    )

    features = FeatureConfig(kind=kind, max_features=200)
    rng = np.random.default_rng(seed)
    centroids = rng.random((vocabulary_size, features.descriptor_length)).astype(np.float32)
    return write_bundle(
        out,
        features=features,
        tree=random_tree(vocabulary_size, seed),
        training_observations=synthetic_observations(20, vocabulary_size, 10, seed),
        quantizer={"type": "kmeans", "files": {"centroids": "vocabulary.npy"}},
        quantizer_files={"vocabulary.npy": centroids},
        training_summary={"synthetic": True},
    )


def make_learned_bundle(out: Path, features=None, vocabulary_size: int = 64, seed: int = 0):
    """A small valid k-means bundle whose ORB descriptor is a random learned projection: (path,
    its LearnedDescription). features: a FeatureConfig with descriptor "learned" (default: 200
    keypoints)."""
    import numpy as np

    from aefabmap_export.bundle_writer import write_bundle
    from aefabmap_runtime.core.features.features import FeatureConfig
    from aefabmap_runtime.core.features.learned_description import BITS, SAMPLES, LearnedDescription
    from aefabmap_runtime.tools.synthetic_observations import random_tree, synthetic_observations

    rng = np.random.default_rng(seed)
    learned = LearnedDescription(rng.integers(-127, 128, (BITS, SAMPLES)).astype(np.int8))
    return write_bundle(
        out,
        features=features or FeatureConfig(max_features=200, descriptor="learned"),
        tree=random_tree(vocabulary_size, seed),
        training_observations=synthetic_observations(20, vocabulary_size, 10, seed),
        quantizer={"type": "kmeans", "files": {"centroids": "vocabulary.npy"}},
        quantizer_files={"vocabulary.npy": rng.random((vocabulary_size, 256)).astype(np.float32)},
        training_summary={"synthetic": True},
        learned=learned,
    ), learned


@pytest.fixture
def synthetic_bundle(tmp_path) -> Path:
    return make_synthetic_bundle(tmp_path / "bundle")


def make_synthetic_tree_bundle(out: Path, vocabulary_size: int = 40, kind: str = "orb", branching: int = 4,
                               seed: int = 0) -> Path:
    """A small valid kmeans-tree bundle, its tree trained on generated descriptor vectors."""
    import numpy as np

    from aefabmap_export.bundle_writer import write_bundle
    from aefabmap_runtime.core.features.features import FeatureConfig
    from aefabmap_runtime.tools.synthetic_observations import random_tree, synthetic_observations
    from aefabmap_trainer.kmeans import KMeansConfig
    from aefabmap_trainer.train import TREE_FILE_NAMES
    from aefabmap_trainer.hierarchical_kmeans import fit_vocab_tree

    features = FeatureConfig(kind=kind, max_features=200)
    rng = np.random.default_rng(seed)
    binary = features.spec.distance == "hamming"
    d = features.descriptor_length
    x = (rng.random((2000, d)) < 0.5).astype(np.float32) if binary else rng.random((2000, d)).astype(np.float32)
    a = fit_vocab_tree(x, vocabulary_size, branching, binary=binary, config=KMeansConfig(4, seed=seed))
    return write_bundle(
        out,
        features=features,
        tree=random_tree(vocabulary_size, seed),
        training_observations=synthetic_observations(20, vocabulary_size, 10, seed),
        quantizer={"type": "kmeans-tree", "files": dict(TREE_FILE_NAMES), "branching": branching,
                   "nodes": int(a.children.shape[0]), "distance": "hamming" if binary else "l2"},
        quantizer_files={TREE_FILE_NAMES["centers"]: a.centers, TREE_FILE_NAMES["children"]: a.children,
                         TREE_FILE_NAMES["leaf_words"]: a.leaf_words},
        training_summary={"synthetic": True},
    )


def cli_args(*argv: str):
    """The Namespace the CLI's own parser makes of `argv` (e.g. "replay", LOG, "--model", B)."""
    from aefabmap.cli.main import build_parser

    return build_parser().parse_args([str(a) for a in argv])


@pytest.fixture(scope="session")
def runtime_install(tmp_path_factory):
    """This checkout's wheel installed with the runtime dependencies only, in a fresh venv
    (tests/runtime_install.py); built once per session, for the tests that run the real install."""
    from tests.runtime_install import build_runtime_install

    return build_runtime_install(tmp_path_factory.mktemp("runtime_install"))
