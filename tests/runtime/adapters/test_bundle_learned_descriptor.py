"""A bundle with the learned ORB descriptor: written, read back, run; and hostile variants refused
with one BundleError line."""

from __future__ import annotations

import json

import numpy as np
import pytest

from aefabmap_runtime.adapters.bundle_reader import DESCRIPTOR_WEIGHTS, load_bundle, load_detector, sha256_file
from aefabmap_runtime.core.features.learned_description import BITS, SAMPLES
from aefabmap_runtime.errors import BundleError
from aefabmap_runtime.tools.synthetic_route import SyntheticConfig, make_demo_sequence
from tests.conftest import make_learned_bundle


def _manifest(bundle) -> dict:
    return json.loads((bundle / "manifest.json").read_text())


def _write_manifest(bundle, manifest: dict) -> None:
    (bundle / "manifest.json").write_text(json.dumps(manifest))


def test_the_projection_is_written_checksummed_and_read_back(tmp_path):
    path, learned = make_learned_bundle(tmp_path / "b")
    m = _manifest(path)
    assert m["features"]["descriptor"] == "learned" and m["descriptor_weights"] == DESCRIPTOR_WEIGHTS
    assert m["files"][DESCRIPTOR_WEIGHTS] == sha256_file(path / DESCRIPTOR_WEIGHTS)
    b = load_bundle(path)
    np.testing.assert_array_equal(b.learned_description.weights, learned.weights)


def test_the_detector_describes_frames_with_the_bundles_projection(tmp_path):
    path, learned = make_learned_bundle(tmp_path / "b")
    frames = tmp_path / "frames"
    make_demo_sequence(frames, n_frames=3, seed=1, size=(320, 240), config=SyntheticConfig(laps=1))
    import cv2

    image = cv2.imread(str(sorted(frames.glob("frame_*.jpg"))[0]))
    det = load_detector(path)
    got = det.prepare(image).features
    keypoints, _, patches = det.extractor.keypoint_patches(image)
    np.testing.assert_array_equal(got.keypoints, keypoints)
    np.testing.assert_array_equal(got.descriptors, learned.bits(patches))
    for _ in range(3):
        det.process(image)


def test_a_brief_bundle_has_no_projection(synthetic_bundle):
    assert load_bundle(synthetic_bundle).learned_description is None


@pytest.mark.parametrize("case", ["missing_key", "unlisted", "outside", "float", "int16", "shape", "zeros", "on_brief"])
def test_a_hostile_projection_is_refused(tmp_path, case):
    path, _ = make_learned_bundle(tmp_path / "b")
    m = _manifest(path)
    if case == "missing_key":
        del m["descriptor_weights"]
    elif case == "unlisted":
        del m["files"][DESCRIPTOR_WEIGHTS]
    elif case == "outside":
        m["descriptor_weights"] = "../" + DESCRIPTOR_WEIGHTS
        m["files"]["../" + DESCRIPTOR_WEIGHTS] = m["files"][DESCRIPTOR_WEIGHTS]
    elif case == "on_brief":
        m["features"]["descriptor"] = "brief"
    else:
        array = {"float": np.ones((BITS, SAMPLES), np.float32), "int16": np.ones((BITS, SAMPLES), np.int16),
                 "shape": np.ones((BITS, SAMPLES + 1), np.int8),
                 "zeros": np.zeros((BITS, SAMPLES), np.int8)}[case]
        np.save(path / DESCRIPTOR_WEIGHTS, array, allow_pickle=False)
        m["files"][DESCRIPTOR_WEIGHTS] = sha256_file(path / DESCRIPTOR_WEIGHTS)
    _write_manifest(path, m)
    with pytest.raises(BundleError) as info:
        load_bundle(path)
    assert "\n" not in str(info.value)
