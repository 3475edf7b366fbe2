"""One frame through the detector: decode -> detect -> result, with bad-frame accounting.

The single per-frame step of every adapter that feeds the detector: the live node
(runtime/aefabmap_runtime/adapters/node.py), replay (runtime/aefabmap_runtime/adapters/replay.py), the sequence evaluation
over image folders and the pipeline benchmark (runtime/tools). A frame that cannot be used
is counted under its reason (:data:`frames.BAD_FRAME_REASONS`: the decoder's reasons, and
``rejected`` when the detector refuses the decoded image) by one :class:`BadFrameCounter`,
and the caller goes on with the next frame.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from aefabmap_runtime.errors import BundleError, InputError
from aefabmap_runtime.adapters.frames import (
    BAD_FRAME_REASONS,
    FrameError,
    decode_frame,
    load_image,
)
from aefabmap_runtime.core.records.messages import FrameResult, LatencySummary, StatsMessage


class FrameProcessor(Protocol):
    """What the frame loop needs from the per-frame core (LoopClosureDetector or a stand-in).
    A processor that also has `prepare`, `process_prepared` and `refuse_prepared` (as the
    detector) can have its frames prepared on other threads (frame_pipeline.py)."""

    manifest: dict

    def process(self, gray: np.ndarray, stamp_ns: int) -> Any: ...


@dataclass
class PreparedInput:
    """One frame made ready off its turn (FrameLoop.prepare_*, any thread): the decoded image
    and the processor's prepared frame, or why it cannot be used (error and its reason);
    decode_ms: the decode time."""

    gray: np.ndarray | None = None
    frame: Any = None
    error: Exception | None = None
    reason: str | None = None
    decode_ms: float = 0.0


@dataclass
class BadFrameCounter:
    """Frames refused, per reason (every reason of BAD_FRAME_REASONS present), and the last
    refusal's message (truncated to 200 characters)."""

    counts: dict[str, int] = field(default_factory=lambda: {r: 0 for r in BAD_FRAME_REASONS})
    last: str = ""

    def count(self, reason: str, message: str) -> None:
        self.counts[reason] = self.counts.get(reason, 0) + 1
        self.last = message[:200]

    @property
    def total(self) -> int:
        return sum(self.counts.values())


@dataclass
class FrameOutcome:
    """What one frame gave: the result (None when the frame was refused, see ``bad_reason``),
    the decoded (H, W) uint8 image (None when undecodable) and the decode time in ms."""

    result: FrameResult | None
    gray: np.ndarray | None = None
    bad_reason: str | None = None
    decode_ms: float = 0.0


class FrameLoop:
    """Feeds frames to one detector and keeps the run's counters.

    strict: raise the InputError instead of counting the frame as bad (an evaluation over
    a ground-truth sequence must not skip a frame silently: indices would shift).
    Counters: frames_in (every frame offered), processed (results), loops, bad.
    """

    def __init__(self, detector: FrameProcessor, *, strict: bool = False) -> None:
        self.detector = detector
        self.strict = strict
        self.bad = BadFrameCounter()
        self.frames_in = 0
        self.processed = 0
        self.loops = 0

    @property
    def prepares(self) -> bool:
        """Whether the processor prepares frames apart from deciding them (see FrameProcessor)."""
        return all(hasattr(self.detector, a) for a in ("prepare", "process_prepared", "refuse_prepared"))

    def prepare_payload(self, payload: bytes | bytearray | memoryview, encoding: str,
                        extract: bool = True) -> PreparedInput:
        """Decode a frame payload and, with `extract` (and a processor that `prepares`), prepare it
        (thread-safe; no counter changes: `finish` counts). Without, `finish` runs `process`."""
        t0 = time.perf_counter()
        try:
            gray = decode_frame(payload, encoding)
        except FrameError as exc:
            return PreparedInput(error=exc, reason=exc.reason)
        return self._prepare(gray, (time.perf_counter() - t0) * 1e3, extract)

    def prepare_file(self, path: str | Path, extract: bool = True) -> PreparedInput:
        """Read, decode and prepare an image file (thread-safe, as `prepare_payload`)."""
        t0 = time.perf_counter()
        try:
            gray = load_image(path)
        except FrameError as exc:
            return PreparedInput(error=exc, reason=exc.reason)
        except InputError as exc:
            return PreparedInput(error=exc, reason="corrupt")
        return self._prepare(gray, (time.perf_counter() - t0) * 1e3, extract)

    def finish(self, prepared: PreparedInput, stamp_ns: int) -> FrameOutcome:
        """Decide a prepared frame (frames in the order they came): what `step` gives for it."""
        self.frames_in += 1
        if prepared.gray is None:
            return self._refuse(prepared.error, prepared.reason)
        if prepared.frame is None and prepared.error is None:
            return self._detect(prepared.gray, stamp_ns, prepared.decode_ms)
        if prepared.error is not None:
            self.detector.refuse_prepared()
            out = self._refuse(prepared.error, prepared.reason)
            out.gray, out.decode_ms = prepared.gray, prepared.decode_ms
            return out
        result = self.detector.process_prepared(prepared.frame, stamp_ns)
        self.processed += 1
        self.loops += bool(result.loop)
        return FrameOutcome(result, prepared.gray, None, prepared.decode_ms)

    def _prepare(self, gray: np.ndarray, decode_ms: float, extract: bool) -> PreparedInput:
        if not (extract and self.prepares):
            return PreparedInput(gray, decode_ms=decode_ms)
        try:
            return PreparedInput(gray, self.detector.prepare(gray), decode_ms=decode_ms)
        except (InputError, BundleError) as exc:  # a model failing on one frame costs that frame
            return PreparedInput(gray, error=exc, reason="rejected", decode_ms=decode_ms)

    def step(self, payload: bytes | bytearray | memoryview, encoding: str, stamp_ns: int) -> FrameOutcome:
        """Decode a frame payload (runtime/aefabmap_runtime/adapters/frames.py encodings) and detect on it."""
        return self.finish(self.prepare_payload(payload, encoding, extract=False), stamp_ns)

    def step_file(self, path: str | Path, stamp_ns: int) -> FrameOutcome:
        """Read and decode an image file, then detect on it."""
        return self.finish(self.prepare_file(path, extract=False), stamp_ns)

    def refuse(self, error: FrameError) -> FrameOutcome:
        """Count a frame its transport could not unwrap (e.g. broken ROS 2 CDR) as bad."""
        self.frames_in += 1
        return self._refuse(error, error.reason)

    def step_image(self, gray: np.ndarray, stamp_ns: int) -> FrameOutcome:
        """Detect on an already decoded grayscale (H, W) uint8 image."""
        self.frames_in += 1
        return self._detect(gray, stamp_ns, 0.0)

    def stats_message(self, *, uptime_s: float, dropped: int = 0, publisher_restarts: int = 0,
                      rss_mb: float | None = None, latency_ms: LatencySummary | None = None,
                      fps: float | None = None) -> StatsMessage:
        """A stats message of this loop's counters (what the caller knows is passed in)."""
        return StatsMessage(
            stamp_ns=time.time_ns(),
            uptime_s=round(uptime_s, 3),
            frames_received=self.frames_in,
            frames_processed=self.processed,
            dropped=dropped,
            publisher_restarts=publisher_restarts,
            bad=dict(self.bad.counts),
            last_bad=self.bad.last,
            loops=self.loops,
            rss_mb=rss_mb,
            latency_ms=latency_ms or LatencySummary(),
            fps=fps,
        )

    def _detect(self, gray: np.ndarray, stamp_ns: int, decode_ms: float) -> FrameOutcome:
        try:
            result = self.detector.process(gray, stamp_ns)
        except (InputError, BundleError) as exc:  # a model failing on one frame costs that frame
            out = self._refuse(exc, "rejected")
            out.gray, out.decode_ms = gray, decode_ms
            return out
        self.processed += 1
        self.loops += bool(result.loop)
        return FrameOutcome(result, gray, None, decode_ms)

    def _refuse(self, exc: InputError | BundleError, reason: str) -> FrameOutcome:
        if self.strict:
            raise exc
        self.bad.count(reason, str(exc))
        return FrameOutcome(None, bad_reason=reason)
