"""Frame publisher: image folders, videos, cameras or arrays as a Zenoh frame stream (test and demo tool)."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from aefabmap_runtime.errors import ConfigError, InputError
from aefabmap_runtime.adapters.frames import encode_frame
from aefabmap_runtime.adapters.zenoh_transport import (
    FramePublisher,
    SessionConfig,
    open_session,
)

#: A frame source: a callable returning a fresh iterator of (payload bytes, encoding) pairs
#: (called again for --loop).
FrameSource = Callable[[], Iterator[tuple[bytes, str]]]

IMAGE_SUFFIXES = {".jpg": "image/jpeg", ".jpeg": "image/jpeg", ".png": "image/png"}
OTHER_IMAGE_SUFFIXES = (".bmp", ".pgm", ".ppm", ".tif", ".tiff", ".webp")


def images_dir_source(directory: str | Path, fmt: str = "jpeg") -> FrameSource:
    """Frames from the image files of a directory, sorted by name.

    JPEG/PNG files are sent as they are (no re-encoding); other formats are decoded and
    encoded as ``fmt``. Raises DataNotFoundError when the directory has no images.
    """
    from aefabmap_runtime.errors import DataNotFoundError

    root = Path(directory)
    if not root.is_dir():
        raise DataNotFoundError(f"image directory {root} does not exist")
    files = sorted(p for p in root.iterdir() if p.suffix.lower() in (*IMAGE_SUFFIXES, *OTHER_IMAGE_SUFFIXES))
    if not files:
        raise DataNotFoundError(f"image directory {root} contains no .jpg/.png images")

    def frames() -> Iterator[tuple[bytes, str]]:
        for p in files:
            try:
                data = p.read_bytes()
            except OSError as exc:
                raise InputError(f"cannot read image {p}: {exc.strerror or exc}") from exc
            enc = IMAGE_SUFFIXES.get(p.suffix.lower())
            if enc is not None:
                yield data, enc
            else:
                img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
                if img is None:
                    raise InputError(f"cannot decode image {p}")
                yield encode_frame(img if img.dtype == np.uint8 else cv2.convertScaleAbs(img), fmt)

    return frames


def _capture_source(open_capture: Callable[[], cv2.VideoCapture], what: str, fmt: str) -> FrameSource:
    def frames() -> Iterator[tuple[bytes, str]]:
        cap = open_capture()
        if not cap.isOpened():
            raise InputError(f"cannot open {what}")
        try:
            while True:
                ok, img = cap.read()
                if not ok or img is None:
                    return
                yield encode_frame(img, fmt)
        finally:
            cap.release()

    return frames


def video_source(path: str | Path, fmt: str = "jpeg") -> FrameSource:
    """Frames of a video file (OpenCV), encoded as fmt; InputError if it cannot be opened."""
    p = Path(path)
    if not p.is_file():
        from aefabmap_runtime.errors import DataNotFoundError

        raise DataNotFoundError(f"video file {p} does not exist")
    return _capture_source(lambda: cv2.VideoCapture(str(p)), f"video {p}", fmt)


def camera_source(index: int, fmt: str = "jpeg") -> FrameSource:
    """Frames of camera ``index`` (OpenCV VideoCapture), encoded as fmt."""
    return _capture_source(lambda: cv2.VideoCapture(int(index)), f"camera {index}", fmt)


def array_source(images: Iterable[np.ndarray], fmt: str = "jpeg") -> FrameSource:
    """Frames from in-memory (H, W[, 3]) uint8 images, encoded once as fmt."""
    encoded = [encode_frame(img, fmt) for img in images]
    return lambda: iter(encoded)


@dataclass
class PublishSummary:
    """What publish_frames did: frames published, seconds, achieved rate (Hz), subscriber seen."""

    published: int
    duration_s: float
    rate_hz: float
    matched: bool
    key: str


def publish_frames(
    session_config: SessionConfig,
    key: str,
    source: FrameSource,
    *,
    rate_hz: float,
    count: int | None = None,
    loop: bool = False,
    stop_event: threading.Event | None = None,
    wait_for_subscriber_s: float = 2.0,
    congestion: str = "drop",
) -> PublishSummary:
    """Publish frames on ``key`` at ``rate_hz`` with a sequence-number attachment.

    count: stop after this many frames (None = until the source ends, or forever with
    loop). loop: restart the source when it ends. wait_for_subscriber_s: wait up to this
    long for a matching subscriber before the first frame (0 = don't). The pacing wait is
    on ``stop_event``, so setting it stops within one frame period.
    """
    if not rate_hz or rate_hz <= 0:
        raise ConfigError(f"rate must be > 0 Hz, got {rate_hz!r}")
    if count is not None and count < 0:
        raise ConfigError(f"count must be >= 0, got {count!r}")
    stop = stop_event or threading.Event()
    period = 1.0 / rate_hz
    published = 0
    session = open_session(session_config)
    try:
        pub = FramePublisher(session, key, congestion=congestion)
        try:
            matched = pub.wait_for_subscriber(wait_for_subscriber_s) if wait_for_subscriber_s > 0 else False
            t0 = time.monotonic()
            next_t = t0
            while not stop.is_set() and (count is None or published < count):
                produced = False
                for payload, encoding in source():
                    produced = True
                    if stop.is_set() or (count is not None and published >= count):
                        break
                    delay = next_t - time.monotonic()
                    if delay > 0 and stop.wait(delay):
                        break
                    pub.put(payload, encoding, stamp_ns=time.time_ns())
                    published += 1
                    next_t = max(next_t + period, time.monotonic() - period)
                if not loop or not produced:
                    break
            duration = time.monotonic() - t0
        finally:
            pub.close()
    finally:
        session.close()
    return PublishSummary(published, duration, published / duration if duration > 0 else 0.0, matched, key)


