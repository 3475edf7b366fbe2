"""A live node built from its RunConfig and its I/O: the composition root of `aefabmap run`.

`run_configured_node` opens the Zenoh session by the ROS 2 and fleet rules (node_session.py),
checks the profile's bundle, loads the detector, opens the map state (node_state.py), starts the
live view, runs the frame loop (node.py) until stopped and closes all of it in order. The
messages go to the node's log, ``aefabmap.run``.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass, field
from pathlib import Path

from aefabmap_runtime.adapters import bundle_reader
from aefabmap_runtime.adapters.map_journal import StateReport
from aefabmap_runtime.adapters.mcap_log import McapLogConfig
from aefabmap_runtime.adapters.node import NodeOptions, run_node, stop_on_signals
from aefabmap_runtime.adapters.node_session import Endpoints, node_session
from aefabmap_runtime.adapters.node_state import NodeState, open_frozen_map
from aefabmap_runtime.adapters.rmw_zenoh import RosOptions
from aefabmap_runtime.adapters.rotating_log import LogRotationConfig
from aefabmap_runtime.adapters.state_dir import SnapshotPolicy
from aefabmap_runtime.adapters.zenoh_exposure import is_loopback_host
from aefabmap_runtime.adapters.zenoh_transport import SessionConfig
from aefabmap_runtime.core.kernels import compiled
from aefabmap_runtime.core.profiles import get_profile
from aefabmap_runtime.core.records.messages import RunSummary, StatsMessage
from aefabmap_runtime.core.run_config import RUN_CONFIG_KEY, RunConfig
from aefabmap_runtime.errors import ConfigError

log = logging.getLogger("aefabmap.run")


@dataclass(frozen=True)
class NodeIO:
    """Where a node's frames come from and its results, log, map and view go.

    key / ros: the Zenoh image key, or the ROS 2 image topic read over rmw_zenoh (exactly one).
    results_key: the JSON results' key (None: the sibling ``lcd`` of the image key or topic).
    endpoints: the Zenoh endpoints given (none: loopback). mcap: the log (file, directory or
    ``{n}`` pattern), log_rotation / mcap_profile / image_every: its rotation, layout and image rate.
    state: the state directory keeping the map (None: not kept), snapshots: its snapshot policy.
    foxglove_port / foxglove_host: the live view (port None: none; 0: any free port; a host beyond
    loopback needs endpoints.allow_exposure, ConfigError otherwise: view_exposure).
    """

    mcap: str | Path
    key: str | None = None
    ros: RosOptions | None = None
    results_key: str | None = None
    endpoints: Endpoints = field(default_factory=Endpoints)
    log_rotation: LogRotationConfig | None = None
    mcap_profile: str = "aefabmap"
    image_every: int = 1
    state: str | Path | None = None
    snapshots: SnapshotPolicy = field(default_factory=SnapshotPolicy)
    foxglove_port: int | None = None
    foxglove_host: str = "127.0.0.1"
    stats_period_s: float = 5.0

    def __post_init__(self) -> None:
        if (self.key is None) == (self.ros is None):
            raise ConfigError("a node reads exactly one of an image key and a ROS 2 topic")
        view_exposure(self.foxglove_port, self.foxglove_host, self.endpoints.allow_exposure)


@dataclass(frozen=True)
class NodeRun:
    """What a node did: the frame loop's summary, and what its state directory keeps (None: no --state)."""

    summary: RunSummary
    state: StateReport | None = None

    def to_dict(self) -> dict:
        doc = self.summary.to_dict()
        if self.state is not None:
            doc["state"] = self.state.to_dict()
        return doc


def run_configured_node(config: RunConfig, io: NodeIO, *, stop_event: threading.Event,
                        ready_event: threading.Event | None = None) -> NodeRun:
    """Build the node of `config` and `io`, run it until `stop_event` is set (SIGINT/SIGTERM set it
    while it runs, when called from the main thread) and close it. ready_event: set once subscribed.
    Raises the AefabmapError of whatever failed (ConfigError, BundleError, StateError, LogError,
    TransportError), after closing what was opened."""
    session = node_session(io.endpoints, ros=io.ros is not None, fleet=config.fleet, logger=log)
    if config.profile is not None:  # before loading: the profile's model or nothing
        get_profile(config.profile).check_bundle(bundle_reader.read_manifest(Path(config.model)))
    _apply_process_settings(config)
    detector = bundle_reader.load_detector(config.model, config.detector)
    state = view = frozen = None
    try:
        if config.localize:  # the map is only read: no journal, no snapshots (node_state.open_frozen_map)
            if io.state is None:
                raise ConfigError("--localize needs --state DIR: the map to localize against")
            frozen = open_frozen_map(io.state, detector, log)
        elif io.state is not None:
            state = NodeState(io.state, detector, io.snapshots, log)
        options = node_options(config, io, session, detector)
        log.info("kernels: %s", compiled.describe())  # once the run's settings and state are accepted
        view = start_live_view(io.foxglove_port, io.foxglove_host, allow_exposure=io.endpoints.allow_exposure)
        with stop_on_signals(stop_event):
            summary = run_node(detector, options, stop_event=stop_event, on_stats=_stats_logger(state),
                               ready_event=ready_event, snapshotter=state.snapshotter if state else None, view=view)
        return NodeRun(summary, state.finish() if state is not None else None)
    finally:
        if view is not None:
            view.close()
        if state is not None:
            state.close()
        if frozen is not None:
            frozen.close()


def node_options(config: RunConfig, io: NodeIO, session: SessionConfig, detector) -> NodeOptions:
    """The frame loop's settings; the log's run metadata holds the whole RunConfig."""
    # The map this run starts from (a loaded state's frame counter, 0: empty), so that a replay of
    # a log set spanning restarts rebuilds each run's map (runtime/aefabmap_runtime/adapters/replay.py).
    map_start = {"frame": getattr(detector, "next_sequence", 0), "places": getattr(detector, "n_places", 0)}
    return NodeOptions(key=io.key if io.ros is None else io.ros.image_key, mcap_path=io.mcap, session=session,
                       queue_size=config.queue, stats_period_s=io.stats_period_s, image_log_every=io.image_every,
                       run_config={RUN_CONFIG_KEY: config.to_dict(), "map_start": map_start},
                       result_key=io.results_key, ros=io.ros, log_rotation=io.log_rotation,
                       log_config=McapLogConfig(profile=io.mcap_profile), fleet=config.fleet,
                       workers=config.workers)


def view_exposure(port: int | None, host: str, allow_exposure: bool) -> bool:
    """True when the live view on `host` is reachable from other hosts (False: no view, or
    loopback only). ConfigError when it is and `allow_exposure` (--allow-exposure) was not given:
    the Foxglove protocol authenticates nobody, so whoever reaches the port sees the camera."""
    if port is None or is_loopback_host(host):
        return False
    if not allow_exposure:
        raise ConfigError(f"--foxglove-host {host or '(empty: every interface)'} would serve the live view (camera "
                          "images, results) to other hosts without authentication: give --allow-exposure to accept "
                          "that, or keep the default 127.0.0.1")
    return True


def start_live_view(port: int | None, host: str = "127.0.0.1", *, allow_exposure: bool = False):
    """The foxglove_view.LiveView serving on `port` (None: no view); ConfigError without foxglove-sdk,
    or for a host beyond loopback without `allow_exposure` (view_exposure; accepted: one warning)."""
    exposed = view_exposure(port, host, allow_exposure)
    if port is None:
        return None
    from aefabmap_runtime.adapters.foxglove_view import FoxgloveServer, LiveView

    server = FoxgloveServer(port=port, host=host)
    log.info("Foxglove live view on ws://%s:%d", server.host, server.port)
    if exposed:
        log.warning("network exposure accepted (--allow-exposure): the Foxglove live view on ws://%s:%d is served "
                    "to other hosts without authentication", server.host, server.port)
    return LiveView(server)


def _apply_process_settings(config: RunConfig) -> None:
    """Process-wide settings a run implies: OpenCV's thread count under a profile."""
    if config.profile is not None:
        import cv2

        cv2.setNumThreads(config.detector.threads)


#: What the node warns once when its log enters a state where it keeps less (rotating_log.RotatingLog.state).
LOG_STATE_WARNINGS = {
    "images_stopped": "log: images are no longer logged: free space on the log's disk is below --log-min-free-mb "
                      "IMAGES; results and stats still are",
    "stopped": "log: nothing is logged any more: free space on the log's disk is below --log-min-free-mb RESULTS; "
               "detection and results go on",
    "failed": "log: the log file cannot be written (a full disk or an I/O error); detection and results go on "
              "and a new file is tried",
}


def _stats_logger(state: NodeState | None):
    """The node's periodic stats line, a warning while the map state falls behind, and one when
    the log starts keeping less (its stats line alone is INFO: an operator filtering on warnings
    would not see that the log stopped)."""
    log_state = ["ok"]

    def on_stats(msg: StatsMessage) -> None:
        log.info(
            "processed %d, dropped %d, bad %d, loops %d, %s fps, latency p50 %s ms p95 %s ms, RSS %s MB, "
            "log %s (%d errors)",
            msg.frames_processed, msg.dropped, msg.bad_total, msg.loops, _fmt(msg.fps),
            _fmt(msg.latency_ms.p50), _fmt(msg.latency_ms.p95), msg.rss_mb, msg.log_state, msg.log_errors,
        )
        if msg.log_state != log_state[0] and msg.log_state is not None:
            if msg.log_state in LOG_STATE_WARNINGS:
                log.warning("%s", LOG_STATE_WARNINGS[msg.log_state])
            elif msg.log_state == "ok":
                log.info("log: writing again")
            log_state[0] = msg.log_state
        if state is not None and state.journal.behind:  # frames the map state could not keep so far
            log.warning("%s", state.journal.report().line())

    return on_stats


def _fmt(v) -> str:
    return "-" if v is None else f"{v:.1f}"
