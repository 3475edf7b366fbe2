"""onnxruntime (resident memory once imported) is imported only where an ONNX graph runs: an
autoencoder bundle's graph, or the int8 product of the flat search over binary descriptors. A
bundle searched without one (float product, vocabulary tree) leaves it out of the process."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

from aefabmap import default_bundle
from aefabmap_runtime.tools.synthetic_route import SyntheticConfig, make_demo_sequence
from tests.conftest import make_synthetic_bundle, make_synthetic_tree_bundle

PROBE = textwrap.dedent(
    """
    import sys
    from pathlib import Path

    import cv2

    from aefabmap import DetectorConfig, load_detector

    bundle, variant, frames = sys.argv[1], sys.argv[2], sorted(Path(sys.argv[3]).glob("frame_*.jpg"))
    detector = load_detector(bundle, DetectorConfig(exclude=2, quantizer_variant=variant))
    for path in frames:
        result = detector.process(cv2.imread(str(path), cv2.IMREAD_GRAYSCALE))
    print(f"{result.sequence + 1} frames, onnxruntime imported: {'onnxruntime' in sys.modules}")
    """
)


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    out = tmp_path_factory.mktemp("frames")
    make_demo_sequence(out, n_frames=6, seed=1, size=(320, 240), config=SyntheticConfig(laps=2))
    return out


def _bundle(kind: str, tmp_path):
    if kind == "shipped":
        return default_bundle()
    if kind == "sift-kmeans":
        return make_synthetic_bundle(tmp_path / kind, kind="sift")
    return make_synthetic_tree_bundle(tmp_path / kind)


@pytest.mark.timeout(300)
@pytest.mark.parametrize("bundle, variant, imported", [
    ("shipped", "flat-fp32", False),  # ORB k-means, the float product: no graph
    ("sift-kmeans", "fp32", False),  # float descriptors: the float product
    ("orb-tree", "fp32", False),  # vocabulary tree: popcount, no graph
    ("shipped", "fp32", True),  # ORB k-means' default flat search: the int8 product graph
])
def test_onnxruntime_is_imported_only_for_a_graph(frames, tmp_path, bundle, variant, imported):
    proc = subprocess.run([sys.executable, "-c", PROBE, str(_bundle(bundle, tmp_path)), variant, str(frames)],
                          capture_output=True, text=True, timeout=240)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.strip() == f"6 frames, onnxruntime imported: {imported}"
