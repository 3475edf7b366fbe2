"""Feature extraction: deterministic, scaled back to original pixels, bad input named."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from aefabmap import ConfigError, ImageDecodeError, InputError
from aefabmap_runtime.adapters.frames import decode_image, load_image
from aefabmap_runtime.core.features.features import (
    FeatureConfig,
    FeatureExtractor,
    descriptor_vectors,
)


def textured(seed=0, shape=(240, 320)):
    rng = np.random.default_rng(seed)
    img = cv2.resize(rng.integers(0, 255, (shape[0] // 8, shape[1] // 8), np.uint8), shape[::-1], interpolation=cv2.INTER_NEAREST)
    return cv2.GaussianBlur(img, (3, 3), 0)


@pytest.mark.parametrize("cfg", [FeatureConfig("orb", 300), FeatureConfig("sift", 200), FeatureConfig("sift", 200, rootsift=True)])
def test_deterministic_and_shaped(cfg):
    img = textured()
    a = FeatureExtractor(cfg).extract(img)
    b = FeatureExtractor(cfg).extract(img.copy())
    assert 0 < len(a) <= cfg.max_features
    np.testing.assert_array_equal(a.descriptors, b.descriptors)
    np.testing.assert_array_equal(a.keypoints, b.keypoints)
    v = descriptor_vectors(a.descriptors, cfg.kind)
    assert v.shape == (len(a), cfg.descriptor_length) and v.dtype == np.float32
    # Keypoints are reported in the original image's pixels even though detection ran at 640 px.
    assert a.keypoints[:, 0].max() < 320 and a.keypoints[:, 1].max() < 240
    if cfg.kind == "sift":
        np.testing.assert_allclose(np.linalg.norm(v, axis=1), 1.0, atol=1e-5)
    else:
        assert set(np.unique(v)) <= {0.0, 1.0}


@pytest.mark.parametrize("kind", ["orb", "sift"])
def test_keypoints_are_the_detectors_strongest_first_in_original_pixels(kind):
    """The extractor's arrays are the OpenCV keypoints' own attributes: strongest response first
    (ties by position), positions and sizes scaled back from the 640-px detection image, which
    is upsampled by the bit-exact bilinear (the plain one rounds otherwise on x86 than on ARM)."""
    img = textured(seed=3)
    ex = FeatureExtractor(FeatureConfig(kind, 150))
    work = cv2.resize(img, (640, 480), interpolation=cv2.INTER_LINEAR_EXACT)
    kps, desc = ex._detector.detectAndCompute(work, None)
    order = sorted(range(len(kps)), key=lambda i: (-np.float32(kps[i].response), np.float32(kps[i].pt[1]),
                                                   np.float32(kps[i].pt[0])))[:150]
    f = ex.extract(img)
    scale = 640 / 320
    np.testing.assert_array_equal(f.keypoints, np.array([kps[i].pt for i in order], np.float32) / np.float32(scale))
    np.testing.assert_array_equal(f.sizes, np.array([kps[i].size for i in order], np.float32) / np.float32(scale))


def test_blank_image_gives_no_features():
    f = FeatureExtractor().extract(np.full((120, 160), 128, np.uint8))
    assert len(f) == 0 and f.descriptors.shape == (0, 32)


def test_path_and_array_agree(tmp_path):
    img = textured(1)
    p = tmp_path / "a.png"
    cv2.imwrite(str(p), img)
    ex = FeatureExtractor()
    np.testing.assert_array_equal(ex.extract(load_image(p)).descriptors, ex.extract(img).descriptors)


def test_bad_inputs(tmp_path):
    with pytest.raises(ImageDecodeError, match="empty"):
        decode_image(b"")
    with pytest.raises(ImageDecodeError, match="not a decodable"):
        decode_image(b"\xff\xd8\xff\xe0 this is not a jpeg")
    ok, jpg = cv2.imencode(".jpg", textured())
    with pytest.raises(ImageDecodeError):
        decode_image(jpg.tobytes()[:200])  # truncated
    big_png = b"\x89PNG\r\n\x1a\n" + b"\x00\x00\x00\rIHDR" + (10000).to_bytes(4, "big") + (8000).to_bytes(4, "big") + b"\x08\x00\x00\x00\x00"
    with pytest.raises(ImageDecodeError, match="exceeds"):
        decode_image(big_png)
    with pytest.raises(InputError, match="cannot read"):
        load_image(tmp_path / "missing.jpg")
    with pytest.raises(ConfigError):
        FeatureConfig(kind="surf")
    with pytest.raises(ConfigError):
        FeatureConfig(kind="orb", rootsift=True)
    with pytest.raises(InputError):
        FeatureExtractor().extract(np.zeros((4, 4), np.uint8))


def test_big_jpeg_header_refused():
    # A 50 MP JPEG would take seconds and hundreds of MB to decode: refuse it from the header.
    img = np.zeros((16, 16), np.uint8)
    ok, jpg = cv2.imencode(".jpg", img)
    data = bytearray(jpg.tobytes())
    i = data.index(b"\xff\xc0")
    data[i + 5 : i + 7] = (5000).to_bytes(2, "big")
    data[i + 7 : i + 9] = (10000).to_bytes(2, "big")
    with pytest.raises(ImageDecodeError, match="exceeds"):
        decode_image(bytes(data))


def _clustered_texture() -> np.ndarray:
    """Dense texture in the left quarter, sparse corners elsewhere (a hedge beside a facade)."""
    rng = np.random.default_rng(0)
    img = np.full((360, 480), 128, np.uint8)
    img[:, :120] = cv2.GaussianBlur(rng.integers(0, 255, (360, 120)).astype(np.uint8), (0, 0), 1.5)
    for x in range(160, 480, 40):
        for y in range(20, 360, 40):
            cv2.rectangle(img, (x, y), (x + 12, y + 12), 105, -1)  # weak corners
    return img


def test_bucketing_spreads_the_keypoint_budget_over_the_image():
    img = _clustered_texture()
    plain = FeatureExtractor(FeatureConfig(kind="orb", max_features=200, long_side=None)).extract(img)
    spread = FeatureExtractor(FeatureConfig(kind="orb", max_features=200, long_side=None, bucket_grid=4)).extract(img)
    right_plain = int((plain.keypoints[:, 0] > 140).sum())
    right_spread = int((spread.keypoints[:, 0] > 140).sum())
    assert len(spread) == 200 and right_spread > 2 * max(right_plain, 1), (right_plain, right_spread)


def test_bundles_without_bucketing_keep_their_extraction():
    # A bundle written before bucket_grid/clahe existed was trained without them.
    cfg = FeatureConfig.from_dict({"kind": "orb", "max_features": 500, "long_side": 640, "rootsift": False})
    assert cfg.bucket_grid == 0 and cfg.clahe is False
    assert FeatureConfig.from_dict(FeatureConfig(bucket_grid=4, clahe=True).to_dict()) == FeatureConfig(bucket_grid=4, clahe=True)
    with pytest.raises(ConfigError):
        FeatureConfig(bucket_grid=-1)


def test_contrast_stretch_brings_a_dark_frame_to_full_range_with_a_capped_gain():
    from aefabmap_runtime.core.features.features import MAX_STRETCH_GAIN, stretch_contrast

    rng = np.random.default_rng(0)
    day = rng.integers(0, 256, (120, 160)).astype(np.uint8)
    dark = (day // 6).astype(np.uint8)  # grey levels 0..42
    out = stretch_contrast(dark)
    assert out.dtype == np.uint8 and out.shape == dark.shape
    assert np.percentile(out, 99) >= 250 and np.percentile(out, 1) <= 5
    assert np.abs(stretch_contrast(day).astype(int) - day).max() <= 3  # already spans 0..255: nearly unchanged
    flat = np.full((120, 160), 100, np.uint8)
    flat[::7, ::7] = 102  # a nearly uniform frame (fog, lens cap): at most MAX_STRETCH_GAIN
    spread = int(stretch_contrast(flat).max()) - int(stretch_contrast(flat).min())
    assert spread <= 2 * MAX_STRETCH_GAIN + 1


def test_contrast_stretch_finds_corners_in_a_dark_frame_and_old_bundles_keep_it_off():
    import cv2

    from aefabmap_runtime.tools.synthetic_route import generate_loop_sequence

    images, _ = generate_loop_sequence(4, seed=0, size=(640, 480))
    gray = cv2.cvtColor(images[0], cv2.COLOR_BGR2GRAY) if images[0].ndim == 3 else images[0]
    dark = (gray.astype(np.float32) * 0.12).astype(np.uint8)
    plain = FeatureExtractor(FeatureConfig(max_features=1000)).extract(dark)
    stretched = FeatureExtractor(FeatureConfig(max_features=1000, contrast_stretch=True)).extract(dark)
    assert len(stretched) > 2 * max(len(plain), 1)
    assert FeatureConfig.from_dict({"kind": "orb"}).contrast_stretch is False  # written before it existed
    assert FeatureConfig.from_dict(FeatureConfig(contrast_stretch=True).to_dict()).contrast_stretch is True
    with pytest.raises(ConfigError):
        FeatureConfig(contrast_stretch="yes")


@pytest.mark.parametrize("kind", ["orb", "sift-upright-test"])
def test_upright_descriptors_are_the_describers_own_at_orientation_zero(kind, sift_with_upright):
    """Features.upright: each kept keypoint described by the kind's own describer with its angle
    set to 0, row for row with the oriented descriptors (OpenCV's compute returns them in
    another order); the oriented descriptors and keypoints are unchanged by asking for them."""
    img = textured(seed=5)
    plain = FeatureExtractor(FeatureConfig(kind, 150)).extract(img)
    ex = FeatureExtractor(FeatureConfig(kind, 150), upright=True)
    f = ex.extract(img)
    assert plain.upright is None
    np.testing.assert_array_equal(f.descriptors, plain.descriptors)
    np.testing.assert_array_equal(f.keypoints, plain.keypoints)
    assert f.upright.shape == f.descriptors.shape and f.upright.dtype == f.descriptors.dtype
    work = cv2.resize(img, (640, 480), interpolation=cv2.INTER_LINEAR_EXACT)
    kps, _ = ex._detector.detectAndCompute(work, None)
    by_position = {(np.float32(k.pt[0]) / np.float32(2), np.float32(k.pt[1]) / np.float32(2)): k for k in kps}
    for row in (0, 7, len(f) - 1):
        k = by_position[tuple(f.keypoints[row])]
        up = cv2.KeyPoint(k.pt[0], k.pt[1], k.size, 0.0, k.response, k.octave)
        _, d = ex._detector.compute(work, [up])
        expected = ex.kind.finish(d, False)[0]
        np.testing.assert_array_equal(f.upright[row], expected)
    # Oriented descriptors turn with the patch, upright ones do not: they differ for most rows.
    assert np.mean(np.any(f.upright != f.descriptors, axis=1)) > 0.5


def test_upright_descriptors_turn_with_the_camera_and_oriented_ones_do_not():
    """Rolling the camera by 90 degrees moves every point; oriented descriptors of a point stay
    close (they turn with the patch), upright ones do not: why the retry keeps the oriented
    descriptors first."""
    img = textured(seed=6, shape=(320, 320))
    ex = FeatureExtractor(FeatureConfig("orb", 300), upright=True)
    a, b = ex.extract(img), ex.extract(np.ascontiguousarray(np.rot90(img)))
    # np.rot90 (counter-clockwise): (x, y) -> (y, W - 1 - x).
    moved = np.c_[a.keypoints[:, 1], 319 - a.keypoints[:, 0]]
    dist = np.linalg.norm(moved[:, None] - b.keypoints[None], axis=2)
    i, j = np.nonzero(dist < 0.5)
    assert i.size > 30
    bits = np.unpackbits(a.descriptors[i] ^ b.descriptors[j], axis=1).sum(axis=1)
    bits_up = np.unpackbits(a.upright[i] ^ b.upright[j], axis=1).sum(axis=1)
    assert np.median(bits) + 30 < np.median(bits_up)


@pytest.fixture
def sift_with_upright():
    """SIFT registered with upright descriptors on (the built-in SIFT has them off: cost)."""
    from aefabmap_runtime.core.features.feature_kinds import FloatKind, register, unregister

    register(FloatKind("sift-upright-test", 128, lambda n: cv2.SIFT_create(nfeatures=n), upright=True))
    yield
    unregister("sift-upright-test")


@pytest.mark.parametrize("kind", ["sift", "akaze-upright-test"])
def test_kinds_without_upright_descriptors_give_none(kind):
    from aefabmap_runtime.core.features.feature_kinds import BinaryKind, register, unregister

    register(BinaryKind("akaze-upright-test", 61, lambda n: cv2.AKAZE_create()))
    try:
        f = FeatureExtractor(FeatureConfig(kind, 100), upright=True).extract(textured())
        assert len(f) and f.upright is None
    finally:
        unregister("akaze-upright-test")
