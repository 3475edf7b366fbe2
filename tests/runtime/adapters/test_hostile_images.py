"""Hostile images: shapes OpenCV cannot handle are refused (bad_shape) before any OpenCV
call, and a fuzz of the decoder + extractor only ever raises aefabmap errors."""

from __future__ import annotations

import json
import subprocess
import sys

import cv2
import numpy as np
import pytest

from aefabmap_runtime.errors import AefabmapError, InputError
from aefabmap_runtime.adapters.frames import (
    BAD_FRAME_REASONS,
    RAW_FORMATS,
    FrameError,
    decode_frame,
)
from aefabmap_runtime.adapters.mcap_log import McapLogWriter
from aefabmap_runtime.core.features.features import (
    MAX_ASPECT_RATIO,
    FeatureConfig,
    FeatureExtractor,
    Features,
    image_shape_problem,
)

#: Cases of the decoder + extractor fuzz (seeded: the same cases on every run).
FUZZ_CASES = 600


def _png(shape, dtype=np.uint8) -> bytes:
    ok, buf = cv2.imencode(".png", np.zeros(shape, dtype))
    assert ok
    return buf.tobytes()


@pytest.mark.parametrize(
    ("payload", "encoding"),
    [
        (_png((4000, 8)), "image/png"),
        (_png((8, 4000)), "image/png"),
        (_png((2, 100), np.uint16), "image/png"),
        (cv2.imencode(".jpg", np.zeros((8, 4000), np.uint8))[1].tobytes(), "image/jpeg"),
        (b"\x00" * 8 * 4_000_000, "mono8;8x4000000"),
        (b"\x00" * 3 * 4000 * 8, "bgr8;4000x8"),
    ],
    ids=["png-8x4000", "png-4000x8", "png16-100x2", "jpeg-4000x8", "mono8-8x4000000", "bgr8-4000x8"],
)
def test_elongated_frames_are_refused_as_bad_shape(payload, encoding):
    with pytest.raises(FrameError) as info:
        decode_frame(payload, encoding)
    assert info.value.reason == "bad_shape" and "bad_shape" in BAD_FRAME_REASONS


@pytest.mark.parametrize(
    ("shape", "config"),
    [
        ((4000, 8), FeatureConfig()),
        ((8, 4000), FeatureConfig(kind="sift")),
        ((4000, 8, 3), FeatureConfig()),
        ((3, 3), FeatureConfig()),
        ((64, 600), FeatureConfig(long_side=32)),  # 9.4:1 resized to 32 px: a 3-px short side
        ((8, 8000), FeatureConfig(long_side=None)),
    ],
)
def test_extractor_refuses_unusable_shapes_with_an_input_error(shape, config):
    with pytest.raises(InputError, match="too small|too elongated|short side"):
        FeatureExtractor(config).extract(np.zeros(shape, np.uint8))


def test_shape_limits_accept_real_camera_shapes():
    for h, w in [(480, 640), (1080, 1920), (1080, 2560), (360, 1280), (192, 240), (8, 8), (64, 640)]:
        assert image_shape_problem(h, w, 640) is None, (h, w)
    assert image_shape_problem(8, 8 * MAX_ASPECT_RATIO + 1) is not None


def _random_image(rng: np.random.Generator) -> np.ndarray:
    """Half camera-like sizes (sides 32-500 px), half extreme ones: sides from 1 px to a few
    thousand (log-uniform), aspect ratios up to ~1000:1; 8 or 16 bit, 1 to 4 channels; at most
    ~200k pixels so that the fuzz stays fast."""
    while True:
        if rng.random() < 0.5:
            h, w = (int(rng.integers(32, 500)) for _ in range(2))
        else:
            h, w = (int(np.exp(rng.uniform(0, np.log(4000)))) for _ in range(2))
        if h * w <= 200_000:
            break
    channels = int(rng.integers(1, 5))
    dtype = np.uint16 if rng.random() < 0.25 else np.uint8
    top = 65535 if dtype == np.uint16 else 255
    # Blocky noise: some texture for the detectors without costing much to generate.
    small = rng.integers(0, top + 1, (max(1, h // 8), max(1, w // 8), channels)).astype(dtype)
    img = cv2.resize(small, (w, h), interpolation=cv2.INTER_NEAREST).reshape(h, w, channels)
    return img[:, :, 0] if channels == 1 and rng.random() < 0.5 else img


def _random_payload(rng: np.random.Generator, img: np.ndarray) -> tuple[bytes, str]:
    h, w = img.shape[:2]
    channels = 1 if img.ndim == 2 else img.shape[2]
    kind = rng.choice(["png", "jpeg", "raw"])
    if kind == "raw" or (kind == "jpeg" and channels in (2, 4)):
        fmt = rng.choice(sorted(RAW_FORMATS))
        payload = np.ascontiguousarray(img.astype(np.uint8)).tobytes()
        encoding = str(rng.choice([f"{fmt};{w}x{h}", f"video/raw;{fmt};{w}x{h}", f"{fmt};{h}x{w}"]))
    else:
        ext = ".png" if kind == "png" else ".jpg"
        src = img if kind == "png" or img.dtype == np.uint8 else (img >> 8).astype(np.uint8)
        if channels == 2:  # no 2-channel PNG in OpenCV: gray + alpha is not writable, use gray
            src = src[:, :, 0]
        ok, buf = cv2.imencode(ext, src)
        assert ok
        payload, encoding = buf.tobytes(), f"image/{kind}"
    mutation = rng.random()
    if mutation < 0.3 and payload:  # truncated
        payload = payload[: int(rng.integers(0, len(payload)))]
    elif mutation < 0.45 and payload:  # a few flipped bytes (headers included)
        arr = bytearray(payload)
        for i in rng.integers(0, len(arr), int(rng.integers(1, 8))):
            arr[int(i)] ^= int(rng.integers(1, 256))
        payload = bytes(arr)
    return payload, encoding


def test_fuzz_decode_and_extract_raise_only_aefabmap_errors():
    rng = np.random.default_rng(20261122)
    extractors = [
        FeatureExtractor(FeatureConfig()),
        FeatureExtractor(FeatureConfig(kind="sift", max_features=100, long_side=320, rootsift=True)),
        FeatureExtractor(FeatureConfig(max_features=50, long_side=None)),
        FeatureExtractor(FeatureConfig(max_features=50, long_side=32)),
    ]
    outcomes = {"features": 0, "refused": 0}
    for case in range(FUZZ_CASES):
        img = _random_image(rng)
        extractor = extractors[case % len(extractors)]
        try:
            if case % 4 == 3:  # the extractor alone, on the raw array (any dtype / channels)
                out = extractor.extract(img)
            else:
                out = extractor.extract(decode_frame(*_random_payload(rng, img)))
        except AefabmapError:
            outcomes["refused"] += 1
            continue
        except Exception as exc:  # the finding: anything else escapes as a traceback
            raise AssertionError(f"case {case}: {img.shape} {img.dtype}: {type(exc).__name__}: {exc}") from exc
        assert isinstance(out, Features)
        outcomes["features"] += 1
    assert sum(outcomes.values()) == FUZZ_CASES
    assert outcomes["features"] > FUZZ_CASES // 10 and outcomes["refused"] > FUZZ_CASES // 10, outcomes


def test_cli_replay_counts_a_bad_shape_and_exits_cleanly(tmp_path):
    from tests.conftest import make_synthetic_bundle

    bundle = make_synthetic_bundle(tmp_path / "bundle")
    log_path = tmp_path / "bad.mcap"
    rng = np.random.default_rng(0)
    good = cv2.imencode(".png", rng.integers(0, 255, (120, 160), np.uint8))[1].tobytes()
    with McapLogWriter(log_path) as log:
        log.write_image(good, "image/png", 1_000, sequence=0)
        log.write_image(_png((4000, 8)), "image/png", 2_000, sequence=1)
        log.write_image(good, "image/png", 3_000, sequence=2)
    proc = subprocess.run(
        [sys.executable, "-m", "aefabmap.cli.main", "replay", str(log_path), "--model", str(bundle)],
        check=False, capture_output=True, text=True, timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    doc = json.loads(proc.stdout.strip().splitlines()[-1])
    assert doc["frames_processed"] == 2 and doc["bad"]["bad_shape"] == 1


@pytest.mark.parametrize("run_config", [{"max_places": "abc"}, {"memory_mb": [1]}, {"max_places": True},
                                        {"memory_mb": float("nan")}, {"run": "x"}, {"run": {"format": 9}},
                                        {"run": {"format": 1, "detector": {"exclude": -1}}},
                                        {"run": {"format": 1, "detector": {"candidates": {"top_k": 0}}}},
                                        {"run": {"format": 1, "detector": {"verification": {"camera": [0, 1, 2, 3]}}}},
                                        {"run": {"format": 1, "detector": {"verification": {"camera": [1e400] * 4}}}},
                                        {"run": {"format": 1, "detector": {"unknown": 1}}},
                                        {"run": {"format": 1, "queue": 10**30}}])
def test_cli_replay_of_a_log_with_hostile_run_config_exits_2_in_one_line(tmp_path, run_config):
    from tests.conftest import make_synthetic_bundle

    bundle = make_synthetic_bundle(tmp_path / "bundle")
    log_path = tmp_path / "cfg.mcap"
    with McapLogWriter(log_path, run_config=run_config):
        pass
    proc = subprocess.run(
        [sys.executable, "-m", "aefabmap.cli.main", "replay", str(log_path), "--model", str(bundle)],
        check=False, capture_output=True, text=True, timeout=120,
    )
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr and len(proc.stderr.strip().splitlines()) == 1


def _jpeg_with_size_behind_app_segments(width: int, height: int, app_bytes: int) -> bytes:
    """A real small JPEG whose frame header (SOF) claims width x height and sits behind APP15
    segments of app_bytes in all: the size is not in the payload's first 64 KiB."""
    jpeg = cv2.imencode(".jpg", np.full((64, 64), 128, np.uint8))[1].tobytes()
    apps = b""
    while app_bytes > 0:
        n = min(app_bytes, 65533)
        apps += b"\xff\xef" + (n + 2).to_bytes(2, "big") + b"\x00" * n
        app_bytes -= n
    out = bytearray(jpeg[:2] + apps + jpeg[2:])
    i = 2
    while True:  # patch the SOF's height and width
        marker, seg_len = out[i + 1], int.from_bytes(out[i + 2:i + 4], "big")
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            out[i + 5:i + 7], out[i + 7:i + 9] = height.to_bytes(2, "big"), width.to_bytes(2, "big")
            return bytes(out)
        i += 2 + seg_len


@pytest.mark.parametrize("app_bytes", [0, 70_000, 300_000])
def test_a_huge_jpeg_is_refused_from_its_header_wherever_the_header_sits(monkeypatch, app_bytes):
    import aefabmap_runtime.adapters.frames as frames

    def no_decode(*_a, **_k):
        raise AssertionError("the pixels were decoded before the size was checked")

    payload = _jpeg_with_size_behind_app_segments(20000, 20000, app_bytes)
    monkeypatch.setattr(frames.cv2, "imdecode", no_decode)
    with pytest.raises(FrameError) as err:
        decode_frame(payload, "image/jpeg")
    assert err.value.reason == "too_large"


def test_a_jpeg_without_a_frame_header_is_refused_without_decoding(monkeypatch):
    import aefabmap_runtime.adapters.frames as frames

    jpeg = cv2.imencode(".jpg", np.full((64, 64), 128, np.uint8))[1].tobytes()
    sos = jpeg.index(b"\xff\xda")
    sof = next(i for i in range(2, sos) if jpeg[i] == 0xFF and jpeg[i + 1] in (0xC0, 0xC1, 0xC2))
    seg = int.from_bytes(jpeg[sof + 2:sof + 4], "big")
    no_sof = jpeg[:sof] + jpeg[sof + 2 + seg:]  # the same JPEG with its frame header cut out
    monkeypatch.setattr(frames.cv2, "imdecode", lambda *_a, **_k: pytest.fail("decoded a JPEG of unknown size"))
    with pytest.raises(FrameError) as err:
        decode_frame(no_sof, "image/jpeg")
    assert err.value.reason == "corrupt"


def test_a_normal_jpeg_with_a_large_exif_block_still_decodes():
    payload = _jpeg_with_size_behind_app_segments(64, 64, 200_000)
    assert decode_frame(payload, "image/jpeg").shape == (64, 64)
