"""Frame payload decoding/encoding (runtime/aefabmap_runtime/adapters/frames.py)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from aefabmap_runtime.errors import ConfigError, ImageDecodeError, InputError
from aefabmap_runtime.adapters.frames import (
    FrameError,
    compressed_format_to_encoding,
    decode_frame,
    encode_frame,
    pack_raw_rows,
    parse_raw_schema,
)

pytestmark = pytest.mark.timeout(30)


@pytest.fixture
def image() -> np.ndarray:
    rng = np.random.default_rng(1)
    img = cv2.resize(rng.integers(0, 256, size=(12, 16), dtype=np.uint8), (64, 48), interpolation=cv2.INTER_NEAREST)
    return img


def test_png_and_raw_roundtrip_exact(image):
    for fmt in ("png", "mono8"):
        payload, enc = encode_frame(image, fmt)
        assert np.array_equal(decode_frame(payload, enc), image)
    payload, enc = encode_frame(image, "mono8")
    assert enc == "mono8;64x48"
    assert np.array_equal(decode_frame(payload, "video/raw;mono8;64x48"), image)


def test_jpeg_and_bgr8_decode_to_gray(image):
    payload, enc = encode_frame(image, "jpeg")
    assert enc == "image/jpeg"
    out = decode_frame(payload, enc)
    assert out.shape == (48, 64) and out.dtype == np.uint8
    assert np.abs(out.astype(int) - image).mean() < 8
    bgr = np.dstack([image, image, image])
    payload, enc = encode_frame(bgr, "bgr8")
    assert enc == "bgr8;64x48" and len(payload) == 64 * 48 * 3
    assert np.array_equal(decode_frame(payload, enc), image)
    # rgb8 with distinct channels converts with RGB weights
    rgb = np.zeros((4, 4, 3), np.uint8)
    rgb[..., 0] = 255  # red
    assert decode_frame(rgb.tobytes(), "rgb8;4x4")[0, 0] == cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)[0, 0]


def test_encoding_with_zenoh_schema_suffix_accepted(image):
    payload, _ = encode_frame(image, "png")
    assert decode_frame(payload, "image/png;whatever").shape == (48, 64)


def _reason(payload, encoding) -> str:
    with pytest.raises(FrameError) as info:
        decode_frame(payload, encoding)
    assert isinstance(info.value, InputError) and isinstance(info.value, ImageDecodeError)
    return info.value.reason


def test_corrupt_jpeg(image):
    payload, enc = encode_frame(image, "jpeg")
    assert _reason(payload[:40], enc) == "corrupt"
    garbled = payload[:2] + b"\x00" * (len(payload) - 2)
    assert _reason(garbled, enc) in ("corrupt", "not_image")


def test_zero_length_payload():
    assert _reason(b"", "image/jpeg") == "empty"
    assert _reason(b"", "mono8;4x4") == "empty"


def test_wrong_encoding(image):
    payload, _ = encode_frame(image, "jpeg")
    for enc in ("text/plain", "application/json", "", "image/gif", "video/raw", "yuv420;64x48", "mono8;64by48"):
        assert _reason(payload, enc) == "wrong_encoding", enc


def test_raw_size_mismatch_names_expected_and_actual():
    with pytest.raises(FrameError) as info:
        decode_frame(b"\x00" * 100, "mono8;10x11")
    assert info.value.reason == "size_mismatch"
    assert "expected 110 bytes" in str(info.value) and "got 100 bytes" in str(info.value)


def _jpeg_header(width: int, height: int) -> bytes:
    sof = b"\xff\xc0" + (17).to_bytes(2, "big") + b"\x08" + height.to_bytes(2, "big") + width.to_bytes(2, "big")
    sof += b"\x03" + b"\x01\x22\x00\x02\x11\x01\x03\x11\x01"
    return b"\xff\xd8" + b"\xff\xe0" + (16).to_bytes(2, "big") + b"JFIF\x00\x01\x01\x00\x00\x01\x00\x01\x00\x00" + sof


def test_50_megapixel_headers_refused_before_decoding():
    assert _reason(_jpeg_header(8000, 6250) + b"\x00" * 64, "image/jpeg") == "too_large"
    png = b"\x89PNG\r\n\x1a\n" + (13).to_bytes(4, "big") + b"IHDR" + (8000).to_bytes(4, "big") + (6250).to_bytes(4, "big")
    assert _reason(png + b"\x08\x00\x00\x00\x00" + b"\x00" * 32, "image/png") == "too_large"
    assert _reason(b"\x00" * 10, "mono8;8000x6250") == "too_large"
    with pytest.raises(FrameError):
        parse_raw_schema("bgr8;10000x5000")


def test_non_image_payload():
    assert _reason(b'{"hello": "world"}', "image/jpeg") == "not_image"
    assert _reason(b"\x00\x01\x02" * 100, "image/png") == "not_image"


def test_encode_frame_refuses_bad_input(image):
    with pytest.raises(ConfigError):
        encode_frame(image, "gif")
    with pytest.raises(ConfigError):
        encode_frame(image.astype(np.float32), "png")


def test_pack_raw_rows_removes_row_padding(image):
    h, w = image.shape
    padded = np.zeros((h, w + 5), np.uint8)
    padded[:, :w] = image
    payload, enc = pack_raw_rows(padded.tobytes(), "mono8", w, h, w + 5)
    assert enc == f"mono8;{w}x{h}"
    assert np.array_equal(decode_frame(payload, enc), image)
    with pytest.raises(FrameError) as info:
        pack_raw_rows(b"\x00" * 10, "mono8", w, h, w)
    assert info.value.reason == "size_mismatch"
    with pytest.raises(FrameError):
        pack_raw_rows(b"\x00" * 10, "yuv420", 2, 2, 4)


def test_compressed_format_mapping():
    assert compressed_format_to_encoding("jpeg") == "image/jpeg"
    assert compressed_format_to_encoding("bgr8; jpeg compressed bgr8") == "image/jpeg"
    assert compressed_format_to_encoding("PNG") == "image/png"
    assert compressed_format_to_encoding("webp").startswith("unknown/")


def test_ros_image_encodings_decode_to_their_gray():
    rng = np.random.default_rng(3)
    gray = rng.integers(0, 256, (12, 16), dtype=np.uint8)
    h, w = gray.shape
    chroma = rng.integers(0, 256, (h, w), dtype=np.uint8)
    yuyv = np.stack([gray, chroma], axis=2)  # Y U Y V ...: luma first in each pixel pair
    uyvy = np.stack([chroma, gray], axis=2)
    assert np.array_equal(decode_frame(yuyv.tobytes(), f"yuv422_yuy2;{w}x{h}"), gray)
    assert np.array_equal(decode_frame(uyvy.tobytes(), f"yuv422;{w}x{h}"), gray)
    assert np.array_equal(decode_frame(uyvy.tobytes(), f"uyvy;{w}x{h}"), gray)
    wide = (gray.astype(np.uint16) << 8) | 0x7F
    assert np.array_equal(decode_frame(wide.astype("<u2").tobytes(), f"mono16;{w}x{h}"), gray)
    payload, enc = pack_raw_rows(wide.astype(">u2").tobytes(), "mono16", w, h, 2 * w, big_endian=True)
    assert np.array_equal(decode_frame(payload, enc), gray)
    flat = np.full((h, w), 90, np.uint8)  # a uniform mosaic demosaics to the same level
    for pattern in ("rggb", "bggr", "gbrg", "grbg"):
        out = decode_frame(flat.tobytes(), f"bayer_{pattern}8;{w}x{h}")
        assert out.shape == (h, w) and np.all(np.abs(out.astype(int) - 90) <= 1)
    with pytest.raises(FrameError) as info:
        decode_frame(b"\x00" * 30, "yuyv;15x1")
    assert info.value.reason == "bad_shape"


def test_bayer_patterns_are_told_apart():
    """A mosaic with only red pixels lit: each pattern puts red elsewhere, so the gray differs."""
    h, w = 8, 8
    red_at = {"rggb": (0, 0), "bggr": (1, 1), "gbrg": (1, 0), "grbg": (0, 1)}
    for pattern, (r, c) in red_at.items():
        mosaic = np.zeros((h, w), np.uint8)
        mosaic[r::2, c::2] = 255
        bgr = cv2.cvtColor(decode_frame(mosaic.tobytes(), f"bayer_{pattern}8;{w}x{h}"), cv2.COLOR_GRAY2BGR)
        # Gray of pure red is ~0.299 * 255 = 76: only the matching pattern sees the lit pixels as red.
        assert 60 <= int(np.median(bgr[2:-2, 2:-2, 0])) <= 90, pattern
