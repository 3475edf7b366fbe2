"""A replay built from its log's RunConfig and its I/O: the composition root of `aefabmap replay`.

`ConfiguredReplay` reads the run's configuration from the log (a ROS bag has none: the defaults),
loads the detector, the map state (--state) and joins the fleet (--fleet), replays the log
(replay.py) with the live view, saves the map, and keeps the view and the fleet up after it
until stopped; leaving it closes all of that in order.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import threading
from dataclasses import dataclass, field

from aefabmap_runtime.errors import ConfigError
from aefabmap_runtime.adapters import bundle_reader
from aefabmap_runtime.adapters.log_set import log_files
from aefabmap_runtime.adapters.mcap_log import RUN_CONFIG_METADATA, McapLogConfig, read_log_metadata
from aefabmap_runtime.adapters.node import stop_on_signals
from aefabmap_runtime.adapters.node_builder import start_live_view, view_exposure
from aefabmap_runtime.adapters.node_session import Endpoints, node_session
from aefabmap_runtime.adapters.node_state import open_frozen_map, open_state
from aefabmap_runtime.adapters.replay import PlaybackConfig, ReplaySummary, replay
from aefabmap_runtime.adapters.ros_bag import is_ros_bag
from aefabmap_runtime.core.fleet.fleet_map import FleetConfig
from aefabmap_runtime.core.run_config import logged_run_config

log = logging.getLogger("aefabmap.replay")


@dataclass(frozen=True)
class ReplayIO:
    """What a replay reads and writes.

    logs: one aefabmap log set (files, directories, globs; one run) or one ROS bag. model: the bundle.
    out: a new log of the replay (None: none), in the mcap_profile layout. check: compare with the
    logged results. topic: the image topic (None: the log's). state: the state directory the map is
    loaded from and saved to (None: none). foxglove_port / foxglove_host: the live view (port None:
    none; a host beyond loopback needs endpoints.allow_exposure, as `run`'s). playback: pace and
    viewer wait. fleet: join it over `endpoints` (None: no network).
    workers: threads that work on frames (frame_pipeline.py; the same results).
    localize: the state's map is only read (node_state.open_frozen_map): nothing inserted or saved.
    """

    logs: tuple[str, ...]
    model: str
    out: str | None = None
    check: bool = False
    topic: str | None = None
    mcap_profile: str = "aefabmap"
    state: str | None = None
    foxglove_port: int | None = None
    foxglove_host: str = "127.0.0.1"
    playback: PlaybackConfig = field(default_factory=PlaybackConfig)
    fleet: FleetConfig | None = None
    endpoints: Endpoints = field(default_factory=Endpoints)
    workers: int = 1
    localize: bool = False

    def __post_init__(self) -> None:
        view_exposure(self.foxglove_port, self.foxglove_host, self.endpoints.allow_exposure)
        if self.localize and self.state is None:
            raise ConfigError("--localize needs --state DIR: the map to localize against")
        if self.localize and self.check:
            raise ConfigError("--check compares with the logged run, which built its map: it does not go with "
                              "--localize")


class ConfiguredReplay:
    """The replay of `io`, as a context manager: entering loads the detector, its map state and
    the fleet; `replay()` replays the log and saves the map; `serve_until_stopped()` keeps the
    view and the fleet up until `stop` (SIGINT/SIGTERM set it from entering on). AefabmapError
    of whatever fails, after closing what was opened."""

    def __init__(self, io: ReplayIO, stop: threading.Event) -> None:
        self.io, self.stop = io, stop
        self.detector = self.fleet = self.view = self.state_dir = None
        self._stack = contextlib.ExitStack()

    def __enter__(self) -> ConfiguredReplay:
        try:
            self._load()
        except BaseException:
            self._stack.close()
            raise
        return self

    def __exit__(self, *exc_info) -> None:
        self._stack.close()

    def _load(self) -> None:
        io = self.io
        # Replay with the whole configuration of the logged run (a bag has none: the defaults).
        bag = len(io.logs) == 1 and is_ros_bag(io.logs[0])
        self.source = io.logs[0] if bag else log_files(list(io.logs))
        logged = {} if bag else read_log_metadata(self.source[0]).get(RUN_CONFIG_METADATA) or {}
        detector_config = logged_run_config(logged).detector
        # --foxglove draws the inlier matches (kept only then; they do not change any decision).
        detector_config = dataclasses.replace(detector_config, verification=dataclasses.replace(
            detector_config.verification, keep_inlier_points=io.foxglove_port is not None))
        self.detector = bundle_reader.load_detector(io.model, detector_config)
        if io.state is not None:
            opened = open_frozen_map if io.localize else open_state
            self.state_dir = opened(io.state, self.detector, log)
            self._stack.callback(self._close_state)
        # A fleet node serves the places of a loaded state too: join once the map is there.
        self.fleet = _join_fleet(io, self.detector, self._stack) if io.fleet is not None else None
        self._stack.enter_context(stop_on_signals(self.stop))
        self._stack.callback(self._close_view)

    def replay(self) -> ReplaySummary:
        """Replay the log (live view started first), then save the map to the state directory."""
        io, playback = self.io, self.io.playback
        self.view = start_live_view(io.foxglove_port, io.foxglove_host, allow_exposure=io.endpoints.allow_exposure)
        if playback.wait_viewer_s is not None:
            log.info("waiting up to %g s for a Foxglove viewer to subscribe", playback.wait_viewer_s)
        summary = replay(self.detector, self.source, out_path=io.out,
                         check=io.check, image_topic=io.topic, view=self.view, playback=playback, stop=self.stop,
                         log_config=McapLogConfig(profile=io.mcap_profile), workers=io.workers,
                         fleet_stats=self.fleet.fleet_stats if self.fleet is not None else None)
        if self.state_dir is not None and not io.localize:
            info = self.state_dir.save(self.detector.state())
            log.info("map state saved to %s: %d places, %d bytes", info.path, info.n_places, info.nbytes)
            self._close_state()
        return summary

    def serve_until_stopped(self) -> None:
        """After the replay: keep the live view and the fleet node up until stopped (none: return)."""
        if (self.view is not None or self.fleet is not None) and not self.stop.is_set():
            serve_until_stopped(self.view, self.fleet, self.stop)

    def _close_state(self) -> None:
        if self.state_dir is not None:
            self.state_dir.close()
            self.state_dir = None

    def _close_view(self) -> None:
        if self.view is not None:
            self.view.close()
            self.view = None


def _join_fleet(io: ReplayIO, detector, stack: contextlib.ExitStack):
    """Open the session and join the fleet (closed by `stack`); the FleetNode following detector."""
    from aefabmap_runtime.adapters.fleet import join_fleet
    from aefabmap_runtime.adapters.zenoh_transport import open_session

    sc = node_session(io.endpoints, fleet=io.fleet, logger=log)
    session = stack.enter_context(open_session(sc))
    return stack.enter_context(join_fleet(session, detector, io.fleet))


def serve_until_stopped(view, fleet, stop: threading.Event) -> None:
    """Keep the Foxglove server of ``view`` and the fleet node ``fleet`` (either may be None) up
    after the replay until ``stop`` (Ctrl-C/SIGTERM)."""
    if view is not None:
        server = view.server
        log.info("replay done; Foxglove server still up on ws://%s:%d until Ctrl-C", server.host, server.port)
    if fleet is not None:
        log.info("replay done; offering %d places to fleet %s as robot %s until Ctrl-C",
                 fleet.fleet_stats().places_served, fleet.config.name, fleet.config.robot)
    stop.wait()
