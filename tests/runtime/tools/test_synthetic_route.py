"""Synthetic loop sequence (runtime/aefabmap_runtime/tools/synthetic_route.py)."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from aefabmap_runtime.errors import ConfigError
from aefabmap_runtime.tools.synthetic_route import (
    generate_loop_sequence,
    make_demo_sequence,
    route_poses,
    write_sequence,
)

pytestmark = pytest.mark.timeout(120)


@pytest.fixture(scope="module")
def seq():
    return generate_loop_sequence(60, seed=3, size=(320, 240))


def test_shapes_types_and_determinism(seq):
    images, gt = seq
    assert len(images) == 60 and all(im.shape == (240, 320) and im.dtype == np.uint8 for im in images)
    assert gt.shape == (60, 60) and gt.dtype == bool
    again, gt2 = generate_loop_sequence(60, seed=3, size=(320, 240))
    assert all(np.array_equal(a, b) for a, b in zip(images, again)) and np.array_equal(gt, gt2)
    other, _ = generate_loop_sequence(60, seed=4, size=(320, 240))
    assert not np.array_equal(images[0], other[0])


def test_ground_truth_structure(seq):
    _, gt = seq
    assert np.array_equal(gt, gt.T) and not gt.diagonal().any()
    # every frame of the second lap revisits some frame of the first lap
    assert gt[30:, :30].any(axis=1).all()
    # temporal neighbours are never revisits
    idx = np.arange(60)
    assert not gt[np.abs(idx[:, None] - idx[None, :]) < 15].any()


def test_enough_orb_corners_and_revisits_look_alike(seq):
    images, gt = seq
    orb = cv2.ORB_create(500)
    counts = [len(orb.detect(im, None)) for im in images[::6]]
    assert min(counts) >= 150  # 320x240; 640x480 frames give the full 500
    bf = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)

    def good_matches(a, b):
        _, da = orb.detectAndCompute(a, None)
        _, db = orb.detectAndCompute(b, None)
        return sum(m.distance < 40 for m in bf.match(da, db))

    i = 40
    j = int(np.flatnonzero(gt[i, :30])[0])
    far = (i + 15) % 30  # a first-lap frame on the other side of the route
    assert not gt[i, far]
    assert good_matches(images[i], images[j]) > 3 * max(1, good_matches(images[i], images[far]))
    # the revisit is not a pixel copy
    assert not np.array_equal(images[i], images[j])


def test_bad_arguments():
    with pytest.raises(ConfigError):
        generate_loop_sequence(10, 0, (1280, 720))
    with pytest.raises(ConfigError):
        generate_loop_sequence(2, 0, (64, 48))
    with pytest.raises(ConfigError):
        route_poses(10, 0, "big")


def test_write_sequence(tmp_path):
    paths = make_demo_sequence(tmp_path / "demo", n_frames=8, seed=1, size=(64, 48))
    assert [p.name for p in paths][:2] == ["frame_000000.jpg", "frame_000001.jpg"] and len(paths) == 8
    gt = np.load(tmp_path / "demo" / "gt.npy", allow_pickle=False)
    assert gt.shape == (8, 8) and gt.dtype == bool
    info = json.loads((tmp_path / "demo" / "sequence.json").read_text())
    assert info["seed"] == 1 and info["n_frames"] == 8
    assert cv2.imread(str(paths[0]), cv2.IMREAD_GRAYSCALE).shape == (48, 64)
    with pytest.raises(ConfigError):
        write_sequence(tmp_path / "x", [np.zeros((4, 4), np.uint8)], np.zeros((2, 2), bool))
