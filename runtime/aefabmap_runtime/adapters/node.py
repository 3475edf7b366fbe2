"""The streaming runtime: Zenoh frames in -> detector -> JSON results out, logged to MCAP.

`run_node` is the board-side loop (the camera side is ``runtime/aefabmap_runtime/tools/publisher.py``); it is
pure of argparse (``node_builder.run_configured_node`` builds its NodeOptions from a RunConfig)
and stops when the caller sets a ``threading.Event`` (`stop_on_signals` sets it from SIGINT/SIGTERM).

The detector is anything with ``process(gray (H, W) uint8, stamp_ns int) -> FrameResult``
and a ``manifest`` dict: the per-frame core ``aefabmap_runtime.core.detector.LoopClosureDetector``
(see ``bundle_reader.load_detector``). Replay (runtime/aefabmap_runtime/adapters/replay.py) drives the same
detector through the same frame loop (runtime/aefabmap_runtime/adapters/frame_loop.py) from a log, so live
and replay share the core.

Per frame: the frame loop (decode -> ``detector.process``; a frame that cannot be used is
counted under its reason and the loop goes on) -> the result plus its transport fields
(``frame_seq``, the publisher's sequence number; ``latency_ms``, taken from the ring ->
result, i.e. decode + detector; ``age_ms``, capture stamp -> result, meaningful only when
the publisher's clock is synchronised with ours) serialised once (runtime/aefabmap_runtime/core/records/messages.py)
-> published on the results key and logged to MCAP with the image. Every
``stats_period_s`` seconds a StatsMessage (frames, drops, bad by reason, RSS in MB, latency
p50/p95 in ms) is published on ``<results key>/stats`` and logged. While it runs the node
holds the liveliness token ``aefabmap/runtime/<zid>`` and answers status queries on
``aefabmap/status/<zid>`` (runtime/aefabmap_runtime/adapters/health.py).
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Self

import numpy as np

from aefabmap_runtime.errors import ConfigError
from aefabmap_runtime.adapters.fleet import FleetNode, join_fleet
from aefabmap_runtime.adapters.frame_loop import FrameProcessor, FrameLoop, FrameOutcome, PreparedInput
from aefabmap_runtime.adapters.frame_pipeline import FramePipeline
from aefabmap_runtime.adapters.health import HealthEndpoint, StatusBoard, peak_rss_mb, rss_mb
from aefabmap_runtime.adapters.locate_service import LocateService
from aefabmap_runtime.adapters.mcap_log import McapLogConfig, McapLogWriter
from aefabmap_runtime.adapters.rmw_zenoh import (
    RosFrameSubscriber,
    RosOptions,
    RosResultPublisher,
)
from aefabmap_runtime.adapters.ros2dds_bridge import BridgeFrameSubscriber, BridgeResultPublisher, home_of
from aefabmap_runtime.adapters.ros_topic_check import ImageTopicCheck
from aefabmap_runtime.adapters.rotating_log import LogRotationConfig, RotatingLog
from aefabmap_runtime.adapters.zenoh_transport import (
    FrameSubscriber,
    ReceivedFrame,
    ResultPublisher,
    SessionConfig,
    locate_key_for,
    open_session,
    result_key_for,
    stats_key_for,
)
from aefabmap_runtime.core.fleet.fleet_map import FleetConfig
from aefabmap_runtime.core.run_config import check_workers
from aefabmap_runtime.core.records.messages import FleetStats, LatencySummary, RunSummary, StatsMessage

__all__ = ["FrameProcessor", "NodeOptions", "RunStats", "RunSummary", "rss_mb", "run_node", "stop_on_signals"]


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
    ros: subscribe to this ROS 2 image topic over rmw_zenoh (runtime/aefabmap_runtime/adapters/rmw_zenoh.py),
    or through zenoh-bridge-ros2dds when ``ros.bridge`` is set (ros2dds_bridge.py), instead of
    ``key`` (which is then only recorded), and also publish results as ROS 2 messages.
    log_rotation: file size limit, disk budget and free-space thresholds of the log set
    (runtime/aefabmap_runtime/adapters/rotating_log.py; mcap_path may then be a directory or a ``{n}`` pattern).
    fleet: join this fleet (runtime/aefabmap_runtime/adapters/fleet.py): offer the own places, verify other robots'.
    workers: threads that work on frames (runtime/aefabmap_runtime/adapters/frame_pipeline.py): the next
    frames received are decoded and extracted while one is decided; the same results, in order.
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
    ros: RosOptions | None = None
    log_rotation: LogRotationConfig | None = None
    fleet: FleetConfig | None = None
    workers: int = 1

    def __post_init__(self) -> None:
        check_workers(self.workers)
        if not self.stats_period_s > 0:
            raise ConfigError(f"stats period must be > 0 s, got {self.stats_period_s!r}")

    @property
    def results_key(self) -> str:
        if self.result_key:
            return self.result_key
        return self.ros.default_results_key if self.ros is not None else result_key_for(self.key)

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
            **({"ros": self.ros.to_dict()} if self.ros is not None else {}),
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
    #: The fleet's counters (FleetNode.fleet_stats) when the node is in a fleet.
    fleet: Callable[[], FleetStats] | None = None

    def latency(self) -> LatencySummary:
        return LatencySummary(_percentile(self.latencies_ms, 50), _percentile(self.latencies_ms, 95))

    def snapshot(self, loop: FrameLoop, uptime_s: float, fps: float) -> StatsMessage:
        rss = rss_mb()
        peak = peak_rss_mb()  # the kernel's high-water mark: a peak between samples counts too
        for value in (rss, peak):
            if value is not None:
                self.peak_rss_mb = max(self.peak_rss_mb, value)
        msg = loop.stats_message(
            uptime_s=uptime_s, dropped=self.dropped, publisher_restarts=self.publisher_restarts,
            rss_mb=None if rss is None else round(rss, 1), latency_ms=self.latency(), fps=round(fps, 2),
        )
        msg.fleet = self.fleet() if self.fleet is not None else None
        return msg


class StatsEmitter:
    """Every ``period_s`` seconds (and on demand) a StatsMessage of the run, serialised once
    and sent to the publisher, the log and the caller's ``on_stats``."""

    def __init__(self, period_s: float, t0: float, loop: FrameLoop, stats: RunStats, drops,
                 pub: ResultPublisher, log: McapLogWriter | RotatingLog,
                 on_stats: Callable[[StatsMessage], None] | None = None, view=None) -> None:
        self.period_s, self.t0, self.view = period_s, t0, view
        self.loop, self.stats, self.drops = loop, stats, drops
        self.pub, self.log, self.on_stats = pub, log, on_stats
        self.next = t0 + period_s
        self._last_t, self._last_n = t0, 0

    def tick(self) -> float:
        """Emit if due; returns how long a receive may block (short: a stop is seen quickly)."""
        now = time.monotonic()
        if now >= self.next:
            self.emit()
            self.next = max(self.next + self.period_s, now + self.period_s / 2)
        return min(0.1, max(0.0, self.next - now))

    def emit(self) -> None:
        now = time.monotonic()
        fps = (self.loop.processed - self._last_n) / max(now - self._last_t, 1e-9)
        self._last_t, self._last_n = now, self.loop.processed
        self.stats.dropped, self.stats.publisher_restarts = self.drops.dropped, self.drops.restarts
        msg = self.stats.snapshot(self.loop, now - self.t0, fps)
        msg.log_errors, msg.log_state = getattr(self.log, "errors", 0), getattr(self.log, "state", None)
        data = msg.to_json_bytes()
        diagnostics = self.pub.publish_stats(data)  # a ROS 2 run's /diagnostics CDR (None without ROS)
        self.log.write_stats(msg, data=data, diagnostics=diagnostics)
        if self.view is not None:
            self.view.on_stats(data, msg.stamp_ns)
        if self.on_stats is not None:
            self.on_stats(msg)


class ResultOutput:
    """Where a frame's result goes: its transport fields added, serialised once, published on
    the results key and logged to MCAP with the frame's image; shown by the live view when one
    is given (runtime/aefabmap_runtime/adapters/foxglove_view.py LiveView)."""

    def __init__(self, pub: ResultPublisher, log: McapLogWriter | RotatingLog, stats: RunStats, view=None) -> None:
        self.pub, self.log, self.stats, self.view = pub, log, stats, view

    def send(self, frame: ReceivedFrame, out: FrameOutcome) -> None:
        if out.result is None:
            return  # refused: counted by the frame loop
        result = out.result
        latency_ms = (time.monotonic_ns() - frame.recv_mono_ns) / 1e6
        result.frame_seq = frame.meta.seq
        result.latency_ms = round(latency_ms, 3)
        result.age_ms = round((time.time_ns() - frame.stamp_ns) / 1e6, 3)
        data = result.to_json_bytes()
        self.pub.publish_result(data)
        self.stats.latencies_ms.append(latency_ms)
        self.log.write_image(frame.payload, frame.encoding, frame.stamp_ns, sequence=result.sequence,
                             gray=out.gray, log_time_ns=frame.recv_ns)
        if self.view is not None:
            self.view.on_frame(frame.payload, frame.encoding, out.gray, result, data)
        self.log.write_result(result, data=data)


class _Transport:
    """The node's Zenoh side: a session, the frame subscriber and the result publisher; for a
    ROS 2 run, the check that its image topic is published (ros_topic_check.py)."""

    def __init__(self, options: NodeOptions) -> None:
        self.session = open_session(options.session)
        self.sub: FrameSubscriber | RosFrameSubscriber | BridgeFrameSubscriber | None = None
        self.pub: ResultPublisher | RosResultPublisher | BridgeResultPublisher | None = None
        self.topic_check: ImageTopicCheck | None = None
        try:
            ros = options.ros
            if ros is not None and ros.bridge is not None:  # ROS 2 over DDS, through zenoh-bridge-ros2dds
                self.sub = BridgeFrameSubscriber(self.session, ros.image_key, queue_size=options.queue_size)
                self.pub = BridgeResultPublisher(self.session, options.results_key, ros)
                self.topic_check = ImageTopicCheck(
                    ros.fq_topic, self.pub.graph.publishers, lambda: self.sub.received, home=home_of(ros.bridge),
                    hint=" (or the bridge's namespace, --ros-bridge NS)")
            elif ros is not None:  # the one place where ROS 2 (rmw_zenoh) replaces plain keys
                self.sub = RosFrameSubscriber(self.session, ros.domain, ros.topic, queue_size=options.queue_size)
                sub = self.sub
                self.pub = RosResultPublisher(self.session, options.results_key, ros,
                                              wire_distro=lambda: (sub.distro, sub.ros_type),
                                              subscription_depth=options.queue_size)
                self.topic_check = ImageTopicCheck(ros.fq_topic, self.pub.watch.publishers, lambda: sub.received,
                                                   home=f"domain {ros.domain}", hint=" (or --ros-domain)")
            else:
                self.sub = FrameSubscriber(self.session, options.key, queue_size=options.queue_size,
                                           ignore_keys=(options.results_key, options.stats_key))
                self.pub = ResultPublisher(self.session, options.results_key)
        except BaseException:
            self.__exit__()
            raise

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc_info) -> None:
        if self.sub is not None:
            self.sub.close()
        if self.pub is not None:
            self.pub.close()
        self.session.close()


def run_node(
    detector: FrameProcessor,
    options: NodeOptions,
    *,
    stop_event: threading.Event,
    on_stats: Callable[[StatsMessage], None] | None = None,
    ready_event: threading.Event | None = None,
    snapshotter=None,
    view=None,
) -> RunSummary:
    """Run the streaming loop until ``stop_event`` is set (or ``options.max_frames`` processed).

    on_stats: called with each stats message. ready_event: set once subscribed (tests and
    supervisors wait on it). snapshotter: keeps the map on disk (runtime/aefabmap_runtime/adapters/state_dir.py
    Snapshotter): ``record_frame()`` before a frame's result is published, ``after_frame()``
    after it, ``final()`` on the normal stop path
    (stop_event / max_frames; StateError when that last snapshot cannot be written). view: a
    foxglove_view.LiveView shown every result and stats message (its log is set to the run's).
    Raises
    LogError (MCAP target not writable: checked before any network activity; the first file is
    created once the session is up, so a start that fails leaves no file behind and no existing
    file is ever overwritten), TransportError (session), ConfigError. Once running, log errors
    are counted in the stats, never raised.
    """
    manifest = getattr(detector, "manifest", None)
    loop, stats, t0 = FrameLoop(detector), RunStats(), time.monotonic()
    log = RotatingLog(options.mcap_path, options.mcap_config(), options.log_rotation,
                      run_config=options.log_metadata(), manifest=manifest if isinstance(manifest, dict) else None)
    board = StatusBoard(image_key=options.key, results_key=options.results_key,
                        manifest=manifest if isinstance(manifest, dict) else None, log=log, t0=t0)
    with _Transport(options) as io, log.open(), _health(io.session, board) as health, \
            _fleet(io.session, detector, options.fleet) as fleet, \
            LocateService(io.session, detector, locate_key_for(options.results_key)):
        if fleet is not None:  # the fleet node follows the detector; the stats and status carry its counters
            stats.fleet = board.fleet_stats = fleet.fleet_stats
        if io.topic_check is not None:  # /diagnostics carries the status; status, the ROS warnings
            io.pub.status_source = lambda: board.status(health.zid)
            board.warnings = lambda: io.pub.warnings() + io.topic_check.warnings()
            board.topic_check = io.topic_check
        if ready_event is not None:
            ready_event.set()
        if view is not None:
            view.attach_log(log)
        emitter = StatsEmitter(options.stats_period_s, t0, loop, stats, io.sub.drops, io.pub, log, on_stats, view)
        output = ResultOutput(io.pub, log, stats, view)
        def decided(frame: ReceivedFrame, outcome: FrameOutcome) -> None:
            board.after_frame(loop, io.sub.drops, outcome.result, loop.detector)  # before the result goes out
            if snapshotter is not None:
                # The frame is in the journal before its result goes out: after a kill -9 the
                # restarted node never reuses a sequence number that was published.
                snapshotter.record_frame()
            output.send(frame, outcome)
            if snapshotter is not None:
                snapshotter.after_frame()  # a snapshot that is due: after the result, not before it

        def counted(frame: ReceivedFrame) -> None:
            if frame.meta.problem:  # the frame is used, its attachment was not (receive time instead)
                loop.bad.count("bad_attachment", frame.meta.problem)

        # Frames in flight (workers > 1): received frames are prepared ahead and decided in order;
        # the node waits for the transport only when none is in flight.
        with FramePipeline(loop, options.workers, before=counted) as pipe:
            while not stop_event.is_set() and (options.max_frames is None or loop.processed < options.max_frames):
                frame = None
                if io.topic_check is not None:
                    io.topic_check.poll()
                if options.max_frames is None or loop.processed + pipe.pending < options.max_frames:
                    wait_s = emitter.tick()
                    frame = io.sub.receive(wait_s if not pipe.pending else 0.0, stop_event)
                    if frame is not None and frame.error is not None:
                        pipe.put_prepared(frame, PreparedInput(error=frame.error, reason=frame.error.reason),
                                          frame.stamp_ns)
                    elif frame is not None:
                        pipe.put_payload(frame, frame.payload, frame.encoding, frame.stamp_ns)
                if pipe.pending and (frame is None or pipe.full):
                    decided(*pipe.take())
            while pipe.pending:  # frames received are decided and published, also on a stop
                decided(*pipe.take())
        emitter.emit()
        if snapshotter is not None:
            snapshotter.final()
    latency = stats.latency()
    return RunSummary(
        frames_received=loop.frames_in, frames_processed=loop.processed, dropped=stats.dropped,
        bad=dict(loop.bad.counts), loops=loop.loops, duration_s=time.monotonic() - t0,
        latency_ms_p50=latency.p50, latency_ms_p95=latency.p95, peak_rss_mb=round(max(stats.peak_rss_mb, peak_rss_mb() or 0.0), 1),
        mcap_path=str(log.files[0] if log.files else options.mcap_path), images_logged=log.images_written,
        result_key=options.results_key, stats_key=options.stats_key,
        log_files=[str(p) for p in log.files], log_files_deleted=log.deleted_count, log_errors=log.errors,
    )


class _fleet:
    """The node's fleet side for the run (None when not in a fleet); asks the fleet for its
    places once at start."""

    def __init__(self, session, detector, config: FleetConfig | None) -> None:
        self.session, self.detector, self.config = session, detector, config
        self.node: FleetNode | None = None

    def __enter__(self) -> FleetNode | None:
        if self.config is not None:
            self.node = join_fleet(self.session, self.detector, self.config)
        return self.node

    def __exit__(self, *exc_info) -> None:
        if self.node is not None:
            self.node.close()


class _health:
    """The node's liveliness token and status queryable (runtime/aefabmap_runtime/adapters/health.py), for the run."""

    def __init__(self, session, board: StatusBoard) -> None:
        self.session, self.board = session, board

    def __enter__(self) -> HealthEndpoint:
        self.endpoint = HealthEndpoint(self.session, self.board)
        return self.endpoint

    def __exit__(self, *exc_info) -> None:
        self.endpoint.close()


class stop_on_signals:
    """Context manager: SIGINT/SIGTERM set ``stop_event`` (previous handlers restored on exit).

    The event is set by a watcher thread, never by the handler itself: a Python signal handler
    runs on the main thread between two bytecodes, possibly while that thread holds the event's
    internal lock (entering or leaving ``Event.wait``), and ``Event.set()`` there would wait for
    that lock forever. The C-level handler writes the signal number to a pipe
    (``signal.set_wakeup_fd``), and the watcher reads it. Only installs handlers when used from
    the main thread (signal module restriction).
    """

    _SIGNALS = ("SIGINT", "SIGTERM")

    def __init__(self, stop_event: threading.Event) -> None:
        self.stop_event = stop_event
        self._saved: dict[int, Any] = {}
        self._pipe: tuple[int, int] | None = None
        self._old_wakeup_fd = -1
        self._watcher: threading.Thread | None = None

    def __enter__(self) -> threading.Event:
        import os
        import signal

        if threading.current_thread() is not threading.main_thread():
            return self.stop_event
        r, w = os.pipe()
        os.set_blocking(w, False)  # the C handler must never block on a full pipe
        self._pipe = (r, w)
        self._old_wakeup_fd = signal.set_wakeup_fd(w, warn_on_full_buffer=False)
        wanted = {int(getattr(signal, name)) for name in self._SIGNALS}
        self._watcher = threading.Thread(target=self._watch, args=(r, wanted), name="stop-on-signals", daemon=True)
        self._watcher.start()
        for sig in wanted:
            self._saved[sig] = signal.signal(sig, _ignore_in_python)
        return self.stop_event

    def _watch(self, fd: int, wanted: set[int]) -> None:
        import os

        while True:
            try:
                data = os.read(fd, 64)
            except OSError:
                return
            if not data:  # write end closed: the block is over
                return
            if wanted.intersection(data):
                self.stop_event.set()

    def __exit__(self, *exc_info) -> None:
        import os
        import signal

        for sig, handler in self._saved.items():
            signal.signal(sig, handler)
        self._saved.clear()
        if self._pipe is not None:
            r, w = self._pipe
            signal.set_wakeup_fd(self._old_wakeup_fd)
            os.close(w)
            if self._watcher is not None:
                self._watcher.join(5)
            os.close(r)
            self._pipe, self._watcher = None, None


def _ignore_in_python(signum, frame) -> None:  # noqa: ARG001 - signal handler signature
    """The Python-level handler of stop_on_signals: the wakeup pipe carries the signal."""
