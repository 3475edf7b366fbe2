"""The learned ORB descriptor: exact bits, patch sampling, the extractor's use of it."""

from __future__ import annotations

import numpy as np
import pytest

from aefabmap_runtime.core.features.features import FeatureConfig, FeatureExtractor
from aefabmap_runtime.core.features.learned_description import (
    BITS,
    PATCH,
    SAMPLES,
    LearnedDescription,
    sample_patches,
)
from aefabmap_runtime.core.kernels import native
from aefabmap_runtime.errors import ConfigError, InputError


def random_weights(seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(-127, 128, (BITS, SAMPLES)).astype(np.int8)


def textured(seed: int = 1, shape=(240, 320)) -> np.ndarray:
    import cv2

    rng = np.random.default_rng(seed)
    small = rng.integers(0, 256, (shape[0] // 8, shape[1] // 8), dtype=np.uint8)
    return cv2.resize(small, (shape[1], shape[0]), interpolation=cv2.INTER_CUBIC)


def test_bits_are_the_signs_of_the_projection_of_the_centred_patch():
    d = LearnedDescription(random_weights())
    rng = np.random.default_rng(2)
    patches = rng.integers(0, 256, (300, SAMPLES), dtype=np.uint8)
    patches[:5] = 255  # flat patches: every projection is 0, no bit set
    p = patches.astype(np.float64)
    want = (p - p.mean(axis=1, keepdims=True)) @ d.weights.T.astype(np.float64) > 1e-9
    got = np.unpackbits(d.bits(patches), axis=1, bitorder="little").astype(bool)
    assert got.shape == (300, BITS) and np.array_equal(got, want)
    assert not got[:5].any()


def test_bits_are_exact_at_the_largest_sums_and_the_closest_ties():
    # +127 on the first half of the samples, -127 on the second.
    w = np.full((BITS, SAMPLES), 127, np.int8)
    w[:, SAMPLES // 2:] = -127
    d = LearnedDescription(w)

    def bits(patch):
        return np.unpackbits(d.bits(patch[None, :].astype(np.uint8)), bitorder="little")

    half = np.r_[np.full(SAMPLES // 2, 255), np.zeros(SAMPLES // 2)]  # the largest products: 4 145 280
    assert bits(half).all() and not bits(half[::-1]).any()
    # A bright flat patch one grey level off on one side: the projection is +-127 out of 8 290 560.
    near = np.full(SAMPLES, 255)
    near[SAMPLES - 1] = 254
    assert bits(near).all()
    near = np.full(SAMPLES, 255)
    near[0] = 254
    assert not bits(near).any()


@pytest.mark.parametrize("weights", [
    np.zeros((BITS, SAMPLES), np.int8),
    np.ones((BITS, SAMPLES), np.float32),
    np.ones((BITS, SAMPLES - 1), np.int8),
    np.ones((BITS + 1, SAMPLES), np.int8),
])
def test_bad_weights_are_refused(weights):
    with pytest.raises(InputError):
        LearnedDescription(weights)


def test_patches_read_the_window_on_the_keypoints_level_and_turn_with_it():
    level0 = textured()
    level1 = textured(seed=3, shape=(200, 267))
    inv = np.array([1.0, 1 / 1.2], np.float32)
    x, y = 100.0, 90.0
    got = sample_patches([level0, level1], inv, np.array([[x, y]], np.float32), np.zeros(1, np.float32),
                         np.zeros(1, np.int32))
    offsets = (np.arange(PATCH) - (PATCH - 1) / 2) * 2  # -15, -13, .. 15: whole pixels
    v, u = np.meshgrid(offsets, offsets, indexing="ij")
    x0, y0 = int(x), int(y)
    assert np.array_equal(got.reshape(PATCH, PATCH), level0[(y0 + v).astype(int), (x0 + u).astype(int)])
    # Turned by 90 degrees: sample (u, v) sits at (x - v, y + u).
    turned = sample_patches([level0, level1], inv, np.array([[x, y]], np.float32), np.full(1, 90.0, np.float32),
                            np.zeros(1, np.int32)).reshape(PATCH, PATCH)
    assert np.array_equal(turned, level0[(y0 + u).astype(int), (x0 - v).astype(int)])
    # On level 1 at the level's own coordinates.
    other = sample_patches([level0, level1], inv, np.array([[x, y]], np.float32), np.zeros(1, np.float32),
                           np.ones(1, np.int32))
    assert not np.array_equal(other, got)
    with pytest.raises(InputError):
        sample_patches([level0], inv[:1], np.array([[x, y]], np.float32), np.zeros(1, np.float32), np.ones(1, np.int32))


def test_a_patch_that_leaves_the_image_repeats_its_edge():
    level0 = textured()
    got = sample_patches([level0], np.ones(1, np.float32), np.array([[0.0, 0.0]], np.float32),
                         np.zeros(1, np.float32), np.zeros(1, np.int32)).reshape(PATCH, PATCH)
    assert got.shape == (PATCH, PATCH) and (got[: PATCH // 2 - 1, 0] == got[0, 0]).all()


def test_the_extractor_describes_with_the_learned_projection():
    d = LearnedDescription(random_weights())
    image = textured(seed=5, shape=(480, 640))
    ex = FeatureExtractor(FeatureConfig(descriptor="learned", max_features=300), upright=True, learned=d)
    f = ex.extract(image)
    brief = FeatureExtractor(FeatureConfig(max_features=300), upright=True).extract(image)
    assert len(f) == len(brief) > 100
    np.testing.assert_array_equal(f.keypoints, brief.keypoints)  # the same ORB keypoints
    assert f.descriptors.shape == (len(f), 32) and f.descriptors.dtype == np.uint8
    assert not np.array_equal(f.descriptors, brief.descriptors)
    assert not np.array_equal(f.descriptors, f.upright)
    # The keypoints' own patches, projected, are the descriptors.
    keypoints, octave, patches = ex.keypoint_patches(image)
    np.testing.assert_array_equal(keypoints, f.keypoints)
    np.testing.assert_array_equal(d.bits(patches), f.descriptors)
    again = FeatureExtractor(FeatureConfig(descriptor="learned", max_features=300), upright=True, learned=d).extract(image)
    np.testing.assert_array_equal(again.descriptors, f.descriptors)


def test_the_learned_descriptor_needs_its_projection_and_orb():
    d = LearnedDescription(random_weights())
    with pytest.raises(ConfigError):
        FeatureExtractor(FeatureConfig(descriptor="learned"))
    with pytest.raises(ConfigError):
        FeatureExtractor(FeatureConfig(), learned=d)
    with pytest.raises(ConfigError):
        FeatureConfig(kind="sift", descriptor="learned")
    with pytest.raises(ConfigError):
        FeatureConfig(descriptor="surf")
    assert FeatureConfig.from_dict({"kind": "orb"}).descriptor == "brief"
    assert FeatureConfig.from_dict(FeatureConfig(descriptor="learned").to_dict()).descriptor == "learned"


@pytest.mark.skipif(not native.available(), reason="the compiled kernels are not built here")
@pytest.mark.parametrize("form", native.LEARNED_FORMS)
def test_the_compiled_kernel_gives_the_numpy_forms_bytes(form):
    # Each compiled form (native.LEARNED_FORMS) runs where the CPU has its instructions, else the
    # next one does: all give numpy's bytes.
    from aefabmap_runtime.core.features.orb_description import blurred, pyramid

    d = LearnedDescription(random_weights(3))
    levels, inv = pyramid(textured(seed=4, shape=(384, 512)), 8, 1.2)
    levels = blurred(levels)
    rng = np.random.default_rng(5)
    n = 3000
    octave = rng.integers(0, len(levels), n).astype(np.int32)
    # Anywhere on level 0's frame and a little beyond it (edges repeat), at any angle; then upright.
    xy = np.column_stack([rng.uniform(-30, 542, n), rng.uniform(-30, 414, n)]).astype(np.float32)
    for angle in (rng.uniform(-720, 720, n).astype(np.float32), np.zeros(n, np.float32)):
        np.testing.assert_array_equal(d.describe(levels, inv, xy, angle, octave, compiled=True, form=form),
                                      d.describe(levels, inv, xy, angle, octave, compiled=False))
    with pytest.raises(InputError):
        d.describe(levels, inv, xy[:1], np.zeros(1, np.float32), np.array([len(levels)], np.int32), compiled=True,
                   form=form)


@pytest.mark.skipif(not native.available(), reason="the compiled kernels are not built here")
@pytest.mark.parametrize("form", native.LEARNED_FORMS)
@pytest.mark.parametrize("lowest", [-128, -127])
def test_the_compiled_kernel_is_exact_at_the_extreme_weights_and_grey_levels(form, lowest):
    # Weights of `lowest` and +127 on black and white pixels: the largest products each form's
    # arithmetic meets (int8 x int8 in int16 on aarch64, a patch lowered by 128 there; without
    # a -128, Advanced SIMD sums two steps' products in int16).
    from aefabmap_runtime.core.features.orb_description import blurred, pyramid

    rng = np.random.default_rng(6)
    weights = rng.choice(np.array([lowest, -127, 127, 0, 1], np.int8), (BITS, SAMPLES))
    weights[:8] = lowest
    weights[8:16] = 127
    d = LearnedDescription(weights)
    cells = rng.integers(0, 2, (24, 32), dtype=np.uint8) * 255
    image = np.kron(cells, np.ones((16, 16), np.uint8))
    image[:, :128] = 255  # flat white: every projection is zero
    levels, inv = pyramid(image, 8, 1.2)
    levels = blurred(levels)
    n = 2000
    octave = rng.integers(0, len(levels), n).astype(np.int32)
    xy = np.column_stack([rng.uniform(-20, 532, n), rng.uniform(-20, 404, n)]).astype(np.float32)
    angle = np.where(np.arange(n) % 2, rng.uniform(0, 360, n), 0).astype(np.float32)
    np.testing.assert_array_equal(d.describe(levels, inv, xy, angle, octave, compiled=True, form=form),
                                  d.describe(levels, inv, xy, angle, octave, compiled=False))


@pytest.mark.skipif(not native.available(), reason="the compiled kernels are not built here")
def test_an_unknown_compiled_form_is_refused():
    d = LearnedDescription(random_weights(3))
    levels = [textured(shape=(64, 64))]
    with pytest.raises(ConfigError, match="form"):
        d.describe(levels, np.ones(1, np.float32), np.full((1, 2), 32, np.float32), np.zeros(1, np.float32),
                   np.zeros(1, np.int32), compiled=True, form="avx9000")
