"""The streaming runtime: Zenoh frames in -> detector -> JSON results out, logged to MCAP.

`run_node` is the board-side loop (the camera side is ``runtime/tools/publisher.py``); it is
pure of argparse (the CLI in ``aefabmap/cli`` builds its NodeOptions) and stops when the
caller sets a ``threading.Event`` (the CLI sets it from SIGINT/SIGTERM).

The detector is anything with ``process(gray (H, W) uint8, stamp_ns int) -> FrameResult``
and a ``manifest`` dict: the per-frame core ``aefabmap.runtime.core.detector.LoopClosureDetector``
(see ``bundle_reader.load_detector``). Replay (runtime/adapters/replay.py) drives the same
detector through the same frame loop (runtime/adapters/frame_loop.py) from a log, so live
and replay share the core.

Per frame: the frame loop (decode -> ``detector.process``; a frame that cannot be used is
counted under its reason and the loop goes on) -> the result plus its transport fields
(``frame_seq``, the publisher's sequence number; ``latency_ms``, taken from the ring ->
result, i.e. decode + detector; ``age_ms``, capture stamp -> result, meaningful only when
the publisher's clock is synchronised with ours) serialised once (runtime/core/messages.py)
-> published on the results key and logged to MCAP with the image. Every
``stats_period_s`` seconds a StatsMessage (frames, drops, bad by reason, RSS in MB, latency
p50/p95 in ms) is published on ``<results key>/stats`` and logged.
"""

from __future__ import annotations

import os
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from aefabmap.errors import ConfigError
from aefabmap.runtime.adapters.frame_loop import Detector, FrameLoop
from aefabmap.runtime.adapters.mcap_log import McapLogConfig, McapLogWriter
from aefabmap.runtime.adapters.zenoh_transport import (
    FrameSubscriber,
    ReceivedFrame,
    ResultPublisher,
    SessionConfig,
    open_session,
    result_key_for,
    stats_key_for,
)
from aefabmap.runtime.core.messages import LatencySummary, RunSummary, StatsMessage

__all__ = ["Detector", "NodeOptions", "RunStats", "RunSummary", "rss_mb", "run_node", "stop_on_signals"]


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


@dataclass(frozen=True)
class NodeOptions:
    """Settings of one streaming run.

    key: image key expression to subscribe to; results go to ``result_key`` (default: the
    sibling ``lcd`` key, see zenoh_transport.result_key_for), stats to ``<result_key>/stats``.
    mcap_path: the log to write. session: the Zenoh session. queue_size: RingChannel length
    (frames). stats_period_s: seconds between stats messages. image_log_every: log every
    n-th image (0 = none; 1 keeps the log replayable exactly). log_config: the MCAP writer's
    other settings. run_config: extra JSON-able settings stored in the log metadata.
    max_frames: stop after this many processed frames (None: run until stopped).
    """

    key: str
    mcap_path: str | Path
    session: SessionConfig = field(default_factory=SessionConfig)
    queue_size: int = 2
    stats_period_s: float = 5.0
    image_log_every: int = 1
    result_key: str | None = None
    log_config: McapLogConfig | None = None
    run_config: dict | None = None
    max_frames: int | None = None

    def __post_init__(self) -> None:
        if not self.stats_period_s > 0:
            raise ConfigError(f"stats period must be > 0 s, got {self.stats_period_s!r}")

    @property
    def results_key(self) -> str:
        return self.result_key or result_key_for(self.key)

    @property
    def stats_key(self) -> str:
        return stats_key_for(self.results_key)

    def mcap_config(self) -> McapLogConfig:
        return McapLogConfig(**{**asdict(self.log_config or McapLogConfig()), "image_every": self.image_log_every})

    def log_metadata(self) -> dict:
        """The run configuration stored in the log (aefabmap.run_config)."""
        return {
            "key": self.key,
            "result_key": self.results_key,
            "stats_key": self.stats_key,
            "session": self.session.to_dict(),
            "queue_size": self.queue_size,
            "stats_period_s": self.stats_period_s,
            "image_log_every": self.image_log_every,
            "started_ns": time.time_ns(),
            **(self.run_config or {}),
        }


@dataclass
class RunStats:
    """What the node adds to the frame loop's counters: transport drops, latencies, RSS."""

    dropped: int = 0
    publisher_restarts: int = 0
    latencies_ms: deque = field(default_factory=lambda: deque(maxlen=2000))
    peak_rss_mb: float = 0.0

    def latency(self) -> LatencySummary:
        return LatencySummary(_percentile(self.latencies_ms, 50), _percentile(self.latencies_ms, 95))

    def snapshot(self, loop: FrameLoop, uptime_s: float, fps: float) -> StatsMessage:
        rss = rss_mb()
        if rss is not None:
            self.peak_rss_mb = max(self.peak_rss_mb, rss)
        return loop.stats_message(
            uptime_s=uptime_s, dropped=self.dropped, publisher_restarts=self.publisher_restarts,
            rss_mb=None if rss is None else round(rss, 1), latency_ms=self.latency(), fps=round(fps, 2),
        )


class StatsClock:
    """When the next stats message is due, and the frame rate since the previous one."""

    def __init__(self, period_s: float, t0: float) -> None:
        self.period_s = period_s
        self.t0 = t0
        self.next = t0 + period_s
        self._last_t, self._last_n = t0, 0

    def due(self, now: float) -> bool:
        if now < self.next:
            return False
        self.next = max(self.next + self.period_s, now + self.period_s / 2)
        return True

    def wait_s(self, now: float) -> float:
        """How long a receive may block (short, so that a stop is seen quickly)."""
        return min(0.1, max(0.0, self.next - now))

    def fps(self, now: float, processed: int) -> float:
        fps = (processed - self._last_n) / max(now - self._last_t, 1e-9)
        self._last_t, self._last_n = now, processed
        return fps


class _Transport:
    """The node's Zenoh side: a session, the frame subscriber and the result publisher."""

    def __init__(self, options: NodeOptions) -> None:
        self.session = open_session(options.session)
        self.sub: FrameSubscriber | None = None
        self.pub: ResultPublisher | None = None
        try:
            self.sub = FrameSubscriber(self.session, options.key, queue_size=options.queue_size,
                                       ignore_keys=(options.results_key, options.stats_key))
            self.pub = ResultPublisher(self.session, options.results_key)
        except BaseException:
            self.close()
            raise

    def close(self) -> None:
        if self.sub is not None:
            self.sub.close()
        if self.pub is not None:
            self.pub.close()
        self.session.close()


def _publish_frame(frame: ReceivedFrame, loop: FrameLoop, stats: RunStats, pub: ResultPublisher,
                   log: McapLogWriter) -> None:
    """One received frame: frame loop -> transport fields -> serialise once -> publish and log."""
    out = loop.step(frame.payload, frame.encoding, frame.stamp_ns)
    if out.result is None:
        return  # counted by the frame loop
    result = out.result
    latency_ms = (time.monotonic_ns() - frame.recv_mono_ns) / 1e6
    result.frame_seq = frame.meta.seq
    result.latency_ms = round(latency_ms, 3)
    result.age_ms = round((time.time_ns() - frame.stamp_ns) / 1e6, 3)
    data = result.to_json_bytes()
    pub.publish_result(data)
    stats.latencies_ms.append(latency_ms)
    log.write_image(frame.payload, frame.encoding, frame.stamp_ns, sequence=result.sequence, gray=out.gray,
                    log_time_ns=frame.recv_ns)
    log.write_result(result, data=data)


def run_node(
    detector: Detector,
    options: NodeOptions,
    *,
    stop_event: threading.Event,
    on_stats: Callable[[StatsMessage], None] | None = None,
    ready_event: threading.Event | None = None,
) -> RunSummary:
    """Run the streaming loop until ``stop_event`` is set (or ``options.max_frames`` processed).

    on_stats: called with each stats message. ready_event: set once subscribed (tests and
    supervisors wait on it). Raises LogError (MCAP not writable; before any network
    activity), TransportError (session), ConfigError.
    """
    manifest = getattr(detector, "manifest", None)
    loop, stats = FrameLoop(detector), RunStats()
    t0 = time.monotonic()
    clock = StatsClock(options.stats_period_s, t0)
    with McapLogWriter(options.mcap_path, options.mcap_config(),
                       manifest=manifest if isinstance(manifest, dict) else None,
                       run_config=options.log_metadata()) as log:
        io = _Transport(options)
        try:
            if ready_event is not None:
                ready_event.set()

            def emit_stats() -> None:
                now = time.monotonic()
                stats.dropped, stats.publisher_restarts = io.sub.drops.dropped, io.sub.drops.restarts
                msg = stats.snapshot(loop, now - t0, clock.fps(now, loop.processed))
                data = msg.to_json_bytes()
                io.pub.publish_stats(data)
                log.write_stats(msg, data=data)
                if on_stats is not None:
                    on_stats(msg)

            while not stop_event.is_set():
                if options.max_frames is not None and loop.processed >= options.max_frames:
                    break
                now = time.monotonic()
                if clock.due(now):
                    emit_stats()
                frame = io.sub.receive(clock.wait_s(now), stop_event)
                if frame is not None:
                    _publish_frame(frame, loop, stats, io.pub, log)
            emit_stats()
        finally:
            io.close()
    return RunSummary(
        frames_received=loop.frames_in,
        frames_processed=loop.processed,
        dropped=stats.dropped,
        bad=dict(loop.bad.counts),
        loops=loop.loops,
        duration_s=time.monotonic() - t0,
        latency_ms_p50=stats.latency().p50,
        latency_ms_p95=stats.latency().p95,
        peak_rss_mb=stats.peak_rss_mb,
        mcap_path=str(options.mcap_path),
        images_logged=log.images_written,
        result_key=options.results_key,
        stats_key=options.stats_key,
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
