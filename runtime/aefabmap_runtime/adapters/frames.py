"""Frame payloads <-> grayscale images: the image contract of the Zenoh stream and the logs.

Pure functions, no I/O. A frame travels as ``(payload bytes, encoding string)``:

- ``image/jpeg`` and ``image/png``: a compressed image (zenoh ``Encoding.IMAGE_JPEG`` /
  ``IMAGE_PNG``; a schema suffix such as ``image/jpeg;foo`` is ignored).
- raw pixels with a schema string ``<format>;<W>x<H>``, either bare (``mono8;640x480``)
  or behind a raw MIME type (``video/raw;mono8;640x480``,
  ``application/octet-stream;bgr8;640x480``). Formats: ``mono8`` (1 byte/pixel),
  ``bgr8``/``rgb8`` (3), ``bgra8``/``rgba8`` (4), ``mono16`` (2, little-endian; the top
  8 bits are used), ``yuv422_yuy2``/``yuyv`` and ``yuv422``/``uyvy`` (2, even width; the luma
  is the gray image), the 8-bit Bayer mosaics ``bayer_rggb8``/``bggr8``/``gbrg8``/``grbg8``
  (1; demosaiced to gray). These are the ``sensor_msgs/Image`` encoding names. Rows are
  tightly packed, so the payload must be exactly ``W * H * bytes_per_pixel`` bytes.

Every refusal raises :class:`FrameError` (an ``ImageDecodeError``, hence an ``InputError``)
whose ``reason`` is one of :data:`BAD_FRAME_REASONS`, so a streaming loop can count bad
frames per reason and keep running.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from aefabmap_runtime.errors import ConfigError, ImageDecodeError, InputError
from aefabmap_runtime.core.features.features import MAX_ASPECT_RATIO, to_gray

#: Reasons a frame is refused (the keys of the node's "bad" counters). ``bad_shape``: too
#: small or too elongated for the feature extractor; ``bad_attachment``: the frame was used,
#: but its Zenoh attachment (seq, stamp, source) was not (see zenoh_transport.FrameMeta).
BAD_FRAME_REASONS = (
    "corrupt", "empty", "wrong_encoding", "size_mismatch", "too_large", "bad_shape", "not_image", "rejected",
    "bad_attachment",
)

#: Raw pixel formats: name -> bytes per pixel.
RAW_FORMATS = {
    "mono8": 1, "8UC1": 1, "bgr8": 3, "rgb8": 3, "8UC3": 3, "bgra8": 4, "rgba8": 4, "8UC4": 4,
    "mono16": 2, "16UC1": 2,
    "yuv422_yuy2": 2, "yuyv": 2, "yuv422": 2, "uyvy": 2,
    "bayer_rggb8": 1, "bayer_bggr8": 1, "bayer_gbrg8": 1, "bayer_grbg8": 1,
}
#: Packed 4:2:2 formats: name -> offset of the first luma byte in each 2-byte pixel.
_YUV422_LUMA_OFFSET = {"yuv422_yuy2": 0, "yuyv": 0, "yuv422": 1, "uyvy": 1}
#: Bayer mosaics (ROS names) -> OpenCV conversion; OpenCV names a pattern by the second row's
#: first two pixels, hence RGGB -> BayerBG (cv_bridge's mapping).
_BAYER_TO_GRAY = {
    "bayer_rggb8": cv2.COLOR_BayerBG2GRAY, "bayer_bggr8": cv2.COLOR_BayerRG2GRAY,
    "bayer_gbrg8": cv2.COLOR_BayerGR2GRAY, "bayer_grbg8": cv2.COLOR_BayerGB2GRAY,
}

ENCODING_JPEG = "image/jpeg"
ENCODING_PNG = "image/png"
#: MIME prefixes accepted in front of a raw schema string.
RAW_MIME_TYPES = ("video/raw", "application/octet-stream", "zenoh/bytes")

_JPEG_MAGIC = b"\xff\xd8"
_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


# Decoding a 50 MP frame would stall a board for seconds and blow the memory cap.
MAX_IMAGE_PIXELS = 40_000_000


class FrameError(ImageDecodeError):
    """A frame payload was refused; ``reason`` is one of BAD_FRAME_REASONS."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


def decode_image(payload: bytes | bytearray | memoryview) -> np.ndarray:
    """Decode a JPEG/PNG payload to a grayscale uint8 image (H, W).

    Raises ImageDecodeError for empty, corrupt payloads; FrameError (an ImageDecodeError)
    ``too_large`` / ``bad_shape`` for sizes refused from the header, before decoding.
    """
    buf = np.frombuffer(payload, dtype=np.uint8)
    if buf.size == 0:
        raise ImageDecodeError("empty image payload (0 bytes)")
    # Read the header first: refuse huge or unusable images before allocating their pixels.
    # A JPEG's frame header may sit behind any number of APP segments: walk them all, and decode
    # no JPEG whose size is unknown (the decoder would allocate whatever its header claims).
    if buf[:2].tobytes() == b"\xff\xd8":
        size = _jpeg_size(memoryview(buf))
        if size is None:
            raise FrameError("corrupt", f"payload of {buf.size} bytes is not a decodable JPEG: no frame header "
                             "before its image data")
    else:
        size = _png_size(buf[:24].tobytes())
    if size is not None and min(size) > 0:  # a zero side is a corrupt header: imdecode refuses it
        check_frame_size(*size)
    image = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)
    if image is None or image.size == 0:
        raise ImageDecodeError(f"payload of {buf.size} bytes is not a decodable JPEG/PNG image")
    check_frame_size(image.shape[1], image.shape[0])  # the header we parsed may have lied
    return image


def check_frame_size(width: int, height: int) -> None:
    """Refuse a frame size: FrameError ``too_large`` over MAX_IMAGE_PIXELS, ``bad_shape`` when a
    side is 0 or the aspect ratio exceeds features.MAX_ASPECT_RATIO (no extractor can use it;
    OpenCV's ORB asserts on such images). Too-small frames are left to the detector."""
    if width * height > MAX_IMAGE_PIXELS:
        raise FrameError("too_large", f"image of {width}x{height} pixels exceeds the limit of {MAX_IMAGE_PIXELS} pixels")
    if min(width, height) < 1 or max(width, height) > MAX_ASPECT_RATIO * min(width, height):
        raise FrameError(
            "bad_shape", f"image of {width}x{height} pixels is not usable (aspect ratio over {MAX_ASPECT_RATIO}:1)"
        )


def _png_size(head: bytes) -> tuple[int, int] | None:
    if len(head) >= 24 and head[:8] == b"\x89PNG\r\n\x1a\n":
        return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
    return None


def _jpeg_size(data: memoryview) -> tuple[int, int] | None:
    """(width, height) from the JPEG frame header (SOF), walking the marker segments from the
    start of the payload; None when the image data (SOS) or the end comes first, or a segment is
    malformed. Costs one step per segment, whatever the segments' sizes."""
    n, i = len(data), 2
    while i + 1 < n:
        if data[i] != 0xFF:
            return None
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte before a marker
            i += 1
            continue
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:  # no length: SOI, TEM, RSTn
            i += 2
            continue
        if marker in (0xDA, 0xD9) or i + 4 > n:  # image data or end before any frame header
            return None
        seg_len = int.from_bytes(data[i + 2:i + 4], "big")
        if seg_len < 2:
            return None
        # SOF0..SOF15 except DHT(C4), JPG(C8), DAC(CC) carry the frame size.
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            if i + 9 > n:
                return None
            return int.from_bytes(data[i + 7:i + 9], "big"), int.from_bytes(data[i + 5:i + 7], "big")
        i += 2 + seg_len
    return None


def load_image(path: str | Path) -> np.ndarray:
    """Read an image file as grayscale uint8 (H, W); raises InputError naming the file."""
    path = Path(path)
    try:
        payload = path.read_bytes()
    except OSError as exc:
        raise InputError(f"cannot read image {path}: {exc.strerror or exc}") from exc
    try:
        return decode_image(payload)
    except ImageDecodeError as exc:
        raise ImageDecodeError(f"{path}: {exc}") from exc



@dataclass(frozen=True)
class RawSchema:
    """Parsed raw-frame schema: pixel format, width and height in pixels."""

    fmt: str
    width: int
    height: int

    @property
    def channels(self) -> int:
        return RAW_FORMATS[self.fmt]

    @property
    def nbytes(self) -> int:
        """Exact payload length in bytes (tightly packed rows)."""
        return self.width * self.height * self.channels

    def __str__(self) -> str:
        return f"{self.fmt};{self.width}x{self.height}"


def parse_raw_schema(schema: str) -> RawSchema:
    """Parse ``"<format>;<W>x<H>"``; raises FrameError (wrong_encoding / too_large)."""
    parts = [p.strip() for p in schema.split(";")]
    if len(parts) != 2:
        raise FrameError("wrong_encoding", f"raw frame schema must look like 'mono8;640x480', got {schema!r}")
    fmt, size = parts
    if fmt not in RAW_FORMATS:
        raise FrameError(
            "wrong_encoding", f"unknown raw pixel format {fmt!r} (known: {', '.join(sorted(RAW_FORMATS))})"
        )
    try:
        w_text, h_text = size.lower().split("x")
        width, height = int(w_text), int(h_text)
    except ValueError:
        raise FrameError("wrong_encoding", f"raw frame size must look like '640x480', got {size!r}") from None
    if width < 1 or height < 1:
        raise FrameError("wrong_encoding", f"raw frame size must be positive, got {width}x{height}")
    check_frame_size(width, height)
    if fmt in _YUV422_LUMA_OFFSET and width % 2:
        raise FrameError("bad_shape", f"{fmt} needs an even width (pixel pairs share chroma), got {width}")
    if fmt in _BAYER_TO_GRAY and min(width, height) < 2:
        raise FrameError("bad_shape", f"{fmt} needs at least 2x2 pixels, got {width}x{height}")
    return RawSchema(fmt, width, height)


def classify_encoding(encoding: str) -> tuple[str, RawSchema | None]:
    """Return ``("jpeg"|"png"|"raw", schema or None)`` for an encoding string.

    Raises FrameError("wrong_encoding") for anything else.
    """
    enc = (encoding or "").strip()
    head, _, rest = enc.partition(";")
    head_l = head.strip().lower()
    if head_l in (ENCODING_JPEG, "image/jpg"):
        return "jpeg", None
    if head_l == ENCODING_PNG:
        return "png", None
    if head_l in RAW_MIME_TYPES:
        if not rest:
            raise FrameError("wrong_encoding", f"raw encoding {enc!r} needs a schema such as 'mono8;640x480'")
        return "raw", parse_raw_schema(rest)
    if head.strip() in RAW_FORMATS:
        return "raw", parse_raw_schema(enc)
    raise FrameError(
        "wrong_encoding",
        f"unsupported frame encoding {enc!r} (expected image/jpeg, image/png or a raw schema such as mono8;640x480)",
    )


def decode_frame(payload: bytes | bytearray | memoryview, encoding: str) -> np.ndarray:
    """Decode a frame payload into a grayscale uint8 image of shape (H, W).

    payload: the bytes as received; encoding: see the module docstring.
    Raises FrameError with a reason from BAD_FRAME_REASONS.
    """
    kind, schema = classify_encoding(encoding)
    buf = memoryview(payload).cast("B") if not isinstance(payload, (bytes, bytearray)) else payload
    if len(buf) == 0:
        raise FrameError("empty", f"empty frame payload (0 bytes, encoding {encoding!r})")
    if kind == "raw":
        assert schema is not None
        if len(buf) != schema.nbytes:
            raise FrameError(
                "size_mismatch",
                f"raw frame {schema}: expected {schema.nbytes} bytes, got {len(buf)} bytes",
            )
        arr = np.frombuffer(buf, dtype=np.uint8)
        if schema.fmt in _BAYER_TO_GRAY:
            return cv2.cvtColor(arr.reshape(schema.height, schema.width), _BAYER_TO_GRAY[schema.fmt])
        if schema.fmt in _YUV422_LUMA_OFFSET:
            pairs = arr.reshape(schema.height, schema.width, 2)
            return np.ascontiguousarray(pairs[:, :, _YUV422_LUMA_OFFSET[schema.fmt]])
        if schema.channels == 2:  # mono16, little-endian: keep the high byte
            return np.ascontiguousarray(arr.reshape(schema.height, schema.width, 2)[:, :, 1])
        if schema.channels == 1:
            return arr.reshape(schema.height, schema.width).copy()
        img = arr.reshape(schema.height, schema.width, schema.channels)
        if schema.fmt.startswith("rgb"):
            code = cv2.COLOR_RGB2GRAY if schema.channels == 3 else cv2.COLOR_RGBA2GRAY
            return cv2.cvtColor(img, code)
        return to_gray(img)
    head = bytes(buf[:8])
    if not (head.startswith(_JPEG_MAGIC) or head.startswith(_PNG_MAGIC)):
        raise FrameError(
            "not_image", f"payload of {len(buf)} bytes labelled {encoding!r} is not a JPEG/PNG image (bad magic)"
        )
    try:
        return decode_image(buf)
    except FrameError:
        raise
    except ImageDecodeError as exc:
        raise FrameError("corrupt", str(exc)) from exc


def encode_frame(image: np.ndarray, fmt: str = "jpeg", *, jpeg_quality: int = 90) -> tuple[bytes, str]:
    """Encode an (H, W) or (H, W, 3) BGR uint8 image for publishing.

    fmt: ``"jpeg"``, ``"png"``, ``"mono8"`` (gray raw) or ``"bgr8"`` (colour raw).
    Returns ``(payload, encoding string)`` that :func:`decode_frame` accepts.
    """
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.ndim not in (2, 3):
        raise ConfigError("image to encode must be an (H, W) or (H, W, 3) uint8 array")
    h, w = image.shape[:2]
    if fmt in ("jpeg", "png"):
        ext = ".jpg" if fmt == "jpeg" else ".png"
        params = [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)] if fmt == "jpeg" else []
        ok, buf = cv2.imencode(ext, image, params)
        if not ok:
            raise ConfigError(f"OpenCV could not encode a {w}x{h} image as {fmt}")
        return buf.tobytes(), ENCODING_JPEG if fmt == "jpeg" else ENCODING_PNG
    if fmt == "mono8":
        gray = to_gray(image)
        return np.ascontiguousarray(gray).tobytes(), f"mono8;{w}x{h}"
    if fmt == "bgr8":
        bgr = image if image.ndim == 3 else cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
        if bgr.shape[2] != 3:
            raise ConfigError(f"bgr8 needs 3 channels, got {bgr.shape}")
        return np.ascontiguousarray(bgr).tobytes(), f"bgr8;{w}x{h}"
    raise ConfigError(f"frame format must be one of jpeg, png, mono8, bgr8; got {fmt!r}")


def compressed_format_to_encoding(fmt: str) -> str:
    """Map a CompressedImage ``format`` field (foxglove or ROS 2) to a frame encoding.

    ``"jpeg"``, ``"jpg"``, ``"bgr8; jpeg compressed bgr8"`` -> image/jpeg; ``"png"`` -> image/png.
    Anything else maps to ``"unknown/<fmt>"`` which decode_frame refuses (wrong_encoding).
    """
    f = (fmt or "").lower()
    if "png" in f:
        return ENCODING_PNG
    if "jpeg" in f or "jpg" in f:
        return ENCODING_JPEG
    return f"unknown/{fmt}"


def encoding_to_compressed_format(encoding: str) -> str:
    """image/jpeg -> "jpeg", image/png -> "png" (the foxglove.CompressedImage format field)."""
    kind, _ = classify_encoding(encoding)
    if kind == "raw":
        raise ConfigError(f"raw encoding {encoding!r} has no compressed format; encode it first")
    return kind


def pack_raw_rows(data: bytes, fmt: str, width: int, height: int, step: int,
                  *, big_endian: bool = False) -> tuple[bytes, str]:
    """Repack a ROS ``sensor_msgs/Image`` buffer (rows of ``step`` bytes) to tight rows.

    big_endian: the message's ``is_bigendian`` (16-bit formats are swapped to little-endian).
    Returns ``(payload, "fmt;WxH")``. Raises FrameError when the buffer is too short or the
    format unknown.
    """
    if fmt not in RAW_FORMATS:
        raise FrameError("wrong_encoding", f"unsupported sensor_msgs/Image encoding {fmt!r}")
    channels = RAW_FORMATS[fmt]
    row = width * channels
    if width < 1 or height < 1:
        raise FrameError("bad_shape", f"sensor_msgs/Image of {width}x{height} pixels is empty")
    check_frame_size(width, height)
    if step < row or len(data) < step * (height - 1) + row:
        raise FrameError(
            "size_mismatch",
            f"sensor_msgs/Image {width}x{height} {fmt} step {step}: expected {step * height} bytes, got {len(data)}",
        )
    if step == row:
        payload = bytes(data[: row * height])
    else:
        arr = np.frombuffer(data, dtype=np.uint8, count=step * (height - 1) + row)
        rows = np.lib.stride_tricks.as_strided(arr, shape=(height, row), strides=(step, 1))
        payload = np.ascontiguousarray(rows).tobytes()
    if big_endian and fmt in ("mono16", "16UC1"):
        payload = np.frombuffer(payload, dtype=">u2").astype("<u2").tobytes()
    return payload, f"{fmt};{width}x{height}"
