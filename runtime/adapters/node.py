"""The streaming runtime: Zenoh frames in -> detector -> JSON results out, logged to MCAP.

`run_node` is the board-side loop (the camera side is ``runtime/tools/publisher.py``); it is
pure of argparse (the CLI in ``aefabmap/cli`` builds its arguments) and stops when the
caller sets a ``threading.Event`` (the CLI sets it from SIGINT/SIGTERM).

The detector is anything with ``process(gray (H, W) uint8, stamp_ns int) -> result`` where
``result.to_dict()`` is JSON-able, and a ``manifest`` dict: the per-frame core
``aefabmap.runtime.core.detector.LoopClosureDetector`` (see ``bundle_reader.load_detector``). Replay
(runtime/adapters/replay.py) drives the same detector from a log, so live and replay share the core.

Per frame: decode (runtime.frames) -> ``detector.process`` -> publish the result dict (plus
``frame_seq``, the publisher's sequence number; ``latency_ms``, taken from the ring -> result,
i.e. decode + detector; ``age_ms``, capture stamp -> result, meaningful only when the
publisher's clock is synchronised with ours) on the results key -> log image + result to MCAP. A frame that cannot be used is counted under
its reason (``corrupt``, ``empty``, ``wrong_encoding``, ``size_mismatch``, ``too_large``,
``not_image``; ``rejected`` when the detector refuses the decoded image) and the loop goes
on. Every ``stats_period_s`` seconds a stats dict (frames, drops, bad by reason, RSS in MB,
latency p50/p95 in ms) is published on ``<results key>/stats`` and logged.
"""

from __future__ import annotations

import os
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from aefabmap.errors import ConfigError, InputError
from aefabmap.runtime.adapters.frames import BAD_FRAME_REASONS, FrameError, decode_frame
from aefabmap.runtime.adapters.mcap_log import McapLogConfig, McapLogWriter
from aefabmap.runtime.adapters.zenoh_transport import (
    FrameSubscriber,
    ResultPublisher,
    SessionConfig,
    open_session,
    result_key_for,
    stats_key_for,
)


class Detector(Protocol):
    """What the node needs from the per-frame core."""

    manifest: dict

    def process(self, gray: np.ndarray, stamp_ns: int) -> Any: ...


def rss_mb() -> float | None:
    """Resident set size of this process in MB (from /proc/self/statm; None elsewhere)."""
    try:
        with open("/proc/self/statm", "rb") as f:
            pages = int(f.read().split()[1])
        return pages * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (OSError, ValueError, IndexError):
        return None


def _percentile(values, q: float) -> float | None:
    if not values:
        return None
    return float(np.percentile(np.fromiter(values, dtype=np.float64), q))


@dataclass
class RunStats:
    """Counters of a run (cumulative)."""

    frames_received: int = 0
    frames_processed: int = 0
    dropped: int = 0
    publisher_restarts: int = 0
    loops: int = 0
    bad: dict[str, int] = field(default_factory=lambda: {r: 0 for r in BAD_FRAME_REASONS})
    last_bad: str = ""
    latencies_ms: deque = field(default_factory=lambda: deque(maxlen=2000))
    peak_rss_mb: float = 0.0

    def snapshot(self, uptime_s: float, fps: float) -> dict:
        rss = rss_mb()
        if rss is not None:
            self.peak_rss_mb = max(self.peak_rss_mb, rss)
        return {
            "stamp_ns": time.time_ns(),
            "uptime_s": round(uptime_s, 3),
            "frames_received": self.frames_received,
            "frames_processed": self.frames_processed,
            "dropped": self.dropped,
            "publisher_restarts": self.publisher_restarts,
            "bad": dict(self.bad),
            "bad_total": sum(self.bad.values()),
            "last_bad": self.last_bad,
            "loops": self.loops,
            "rss_mb": None if rss is None else round(rss, 1),
            "latency_ms": {
                "p50": _percentile(self.latencies_ms, 50),
                "p95": _percentile(self.latencies_ms, 95),
            },
            "fps": round(fps, 2),
        }


@dataclass
class RunSummary:
    """What a run did. Latencies in ms (receive -> result), RSS in MB, duration in s."""

    frames_received: int
    frames_processed: int
    dropped: int
    bad: dict[str, int]
    loops: int
    duration_s: float
    latency_ms_p50: float | None
    latency_ms_p95: float | None
    peak_rss_mb: float
    mcap_path: str
    images_logged: int
    result_key: str
    stats_key: str

    @property
    def bad_total(self) -> int:
        return sum(self.bad.values())

    def to_dict(self) -> dict:
        d = asdict(self)
        d["bad_total"] = self.bad_total
        return d


def run_node(
    detector: Detector,
    session_config: SessionConfig,
    key: str,
    mcap_path: str | Path,
    *,
    queue_size: int = 2,
    stop_event: threading.Event,
    stats_period_s: float = 5.0,
    image_log_every: int = 1,
    result_key: str | None = None,
    log_config: McapLogConfig | None = None,
    run_config: dict | None = None,
    max_frames: int | None = None,
    on_stats: Callable[[dict], None] | None = None,
    ready_event: threading.Event | None = None,
) -> RunSummary:
    """Run the streaming loop until ``stop_event`` is set (or ``max_frames`` processed).

    key: image key expression to subscribe to; results go to ``result_key`` (default: the
    sibling ``lcd`` key, see runtime.zenoh_io). queue_size: RingChannel length (frames).
    stats_period_s: seconds between stats messages. image_log_every: log every n-th
    image (0 = none; 1 keeps the log replayable exactly). run_config: extra JSON-able
    settings stored in the log metadata. on_stats: called with each stats dict.
    ready_event: set once subscribed (tests and supervisors wait on it).

    Raises LogError (MCAP not writable), TransportError (session), ConfigError.
    """
    if stats_period_s <= 0:
        raise ConfigError(f"stats period must be > 0 s, got {stats_period_s!r}")
    rkey = result_key or result_key_for(key)
    skey = stats_key_for(rkey)
    base_log = log_config or McapLogConfig()
    log_cfg = McapLogConfig(**{**asdict(base_log), "image_every": image_log_every})
    meta = {
        "key": key,
        "result_key": rkey,
        "stats_key": skey,
        "session": session_config.to_dict(),
        "queue_size": queue_size,
        "stats_period_s": stats_period_s,
        "image_log_every": image_log_every,
        "started_ns": time.time_ns(),
        **(run_config or {}),
    }
    manifest = getattr(detector, "manifest", None)
    stats = RunStats()
    t0 = time.monotonic()
    with McapLogWriter(mcap_path, log_cfg, manifest=manifest if isinstance(manifest, dict) else None,
                       run_config=meta) as log:
        session = open_session(session_config)
        sub = pub = None
        try:
            sub = FrameSubscriber(session, key, queue_size=queue_size, ignore_keys=(rkey, skey))
            pub = ResultPublisher(session, rkey)
            if ready_event is not None:
                ready_event.set()
            next_stats = t0 + stats_period_s
            last_stats_t, last_stats_n = t0, 0

            def emit_stats() -> None:
                nonlocal last_stats_t, last_stats_n
                now = time.monotonic()
                fps = (stats.frames_processed - last_stats_n) / max(now - last_stats_t, 1e-9)
                last_stats_t, last_stats_n = now, stats.frames_processed
                stats.dropped, stats.publisher_restarts = sub.drops.dropped, sub.drops.restarts
                stats.bad["bad_attachment"] = sub.bad_attachments  # frames used, their attachment not
                doc = stats.snapshot(now - t0, fps)
                pub.publish_stats(doc)
                log.write_stats(doc)
                if on_stats is not None:
                    on_stats(doc)

            while not stop_event.is_set():
                if max_frames is not None and stats.frames_processed >= max_frames:
                    break
                now = time.monotonic()
                if now >= next_stats:
                    emit_stats()
                    next_stats = max(next_stats + stats_period_s, now + stats_period_s / 2)
                frame = sub.receive(min(0.1, max(0.0, next_stats - now)), stop_event)
                if frame is None:
                    continue
                stats.frames_received += 1
                try:
                    gray = decode_frame(frame.payload, frame.encoding)
                except FrameError as exc:
                    stats.bad[exc.reason] = stats.bad.get(exc.reason, 0) + 1
                    stats.last_bad = str(exc)[:200]
                    continue
                try:
                    result = detector.process(gray, frame.stamp_ns)
                except InputError as exc:
                    stats.bad["rejected"] += 1
                    stats.last_bad = str(exc)[:200]
                    continue
                doc = dict(result.to_dict())
                latency_ms = (time.monotonic_ns() - frame.recv_mono_ns) / 1e6
                doc["frame_seq"] = frame.meta.seq
                doc["latency_ms"] = round(latency_ms, 3)
                doc["age_ms"] = round((time.time_ns() - frame.stamp_ns) / 1e6, 3)
                pub.publish_result(doc)
                stats.frames_processed += 1
                stats.latencies_ms.append(latency_ms)
                if doc.get("loop"):
                    stats.loops += 1
                seq = doc.get("sequence")
                seq = seq if isinstance(seq, int) else stats.frames_processed - 1
                log.write_image(frame.payload, frame.encoding, frame.stamp_ns, sequence=seq, gray=gray,
                                log_time_ns=frame.recv_ns)
                log.write_result(doc)
            emit_stats()
        finally:
            if sub is not None:
                sub.close()
            if pub is not None:
                pub.close()
            session.close()
    return RunSummary(
        frames_received=stats.frames_received,
        frames_processed=stats.frames_processed,
        dropped=stats.dropped,
        bad=dict(stats.bad),
        loops=stats.loops,
        duration_s=time.monotonic() - t0,
        latency_ms_p50=_percentile(stats.latencies_ms, 50),
        latency_ms_p95=_percentile(stats.latencies_ms, 95),
        peak_rss_mb=stats.peak_rss_mb,
        mcap_path=str(mcap_path),
        images_logged=log.images_written,
        result_key=rkey,
        stats_key=skey,
    )


class stop_on_signals:
    """Context manager: SIGINT/SIGTERM set ``stop_event`` (previous handlers restored on exit).

    Only installs handlers when used from the main thread (signal module restriction).
    """

    def __init__(self, stop_event: threading.Event) -> None:
        self.stop_event = stop_event
        self._saved: dict[int, Any] = {}

    def __enter__(self) -> threading.Event:
        import signal

        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._saved[sig] = signal.signal(sig, self._handle)
        return self.stop_event

    def _handle(self, signum, frame) -> None:  # noqa: ARG002 - signal handler signature
        self.stop_event.set()

    def __exit__(self, *exc_info) -> None:
        import signal

        for sig, handler in self._saved.items():
            signal.signal(sig, handler)
        self._saved.clear()
