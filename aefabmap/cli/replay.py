"""``aefabmap replay``: run a bundle over the images of an MCAP log (own log or ROS 2 bag).

Exit code: 0, or 1 when ``--check`` finds results that differ from the logged ones;
errors exit with the code of their aefabmap_runtime.errors class. With ``--foxglove`` the replay plays at
the recorded pace (``--rate``), optionally after the first viewer (``--wait-viewer``), and the
server stays up after it until Ctrl-C/SIGTERM (docs/streaming.md, "Replay in Foxglove"). With
``--fleet NAME --robot ID`` the replay joins a fleet as `run` does (docs/fleet.md): the map it
builds from the log is offered to the other robots, during the replay and after it until
Ctrl-C/SIGTERM.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import logging
import threading

from aefabmap_runtime.errors import AefabmapError, ConfigError, LogError

log = logging.getLogger("aefabmap.replay")


def register(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "replay",
        help="replay an MCAP log (or ROS 2 bag) through a model bundle",
        description="Run the detector over the logged images; optionally write a new log (--out) and "
        "compare with the logged results (--check; deterministic fields only, not timings).",
    )
    p.add_argument("log", metavar="LOG", nargs="+",
                   help="aefabmap MCAP log (several files, a directory of rotated files or a glob are read in run "
                   "order as one run), or a ROS bag: rosbag2 directory (metadata.yaml), .db3 or .mcap file, "
                   "ROS 1 .bag (needs aefabmap[ros], except ROS 2 .mcap)")
    p.add_argument("--topic", default=None, metavar="TOPIC",
                   help="image topic to replay (required when the bag has several image topics)")
    p.add_argument("--model", required=True, metavar="BUNDLE", help="model bundle directory")
    p.add_argument("--out", default=None, metavar="NEW.mcap", help="write the replayed run to this MCAP")
    p.add_argument("--check", action="store_true", help="compare with the results in the log")
    from aefabmap.cli.run import add_mcap_profile_option

    add_mcap_profile_option(p)
    from aefabmap.cli.state_options import add_state_options

    add_state_options(p)
    from aefabmap.cli.run import add_foxglove_options

    add_foxglove_options(p)
    add_playback_options(p)
    from aefabmap.cli.run import add_fleet_options, add_zenoh_options

    add_zenoh_options(p, add_fleet_options(p))
    p.epilog = ("Network (--fleet only): with none of --connect/--listen/--config the replay listens on "
                "tcp/127.0.0.1:7447 only, as `run` does; no multicast scouting.")
    p.set_defaults(func=main)
    return p


#: Longest wait (s) for a viewer when --wait-viewer is given without a value.
DEFAULT_WAIT_VIEWER_S = 120.0


def add_playback_options(p: argparse.ArgumentParser) -> None:
    """--rate and --wait-viewer (replay.PlaybackConfig)."""
    p.add_argument("--rate", type=float, default=None, metavar="X",
                   help="play at X times the recorded pace (the logged capture stamps; a long pause in the log "
                   "waits a few seconds at most); 0: as fast as possible (default: 1 with --foxglove, else 0)")
    p.add_argument("--wait-viewer", type=float, nargs="?", const=DEFAULT_WAIT_VIEWER_S, default=None,
                   metavar="S", help="with --foxglove: start once a viewer has subscribed, waiting at most S "
                   f"seconds (default {DEFAULT_WAIT_VIEWER_S:g}); at the end the server stays up until Ctrl-C")


def playback_config(args: argparse.Namespace):
    """The PlaybackConfig of the parsed options (ConfigError when invalid)."""
    from aefabmap_runtime.adapters.replay import PlaybackConfig

    if args.wait_viewer is not None and args.foxglove is None:
        raise ConfigError("--wait-viewer needs --foxglove")
    rate = args.rate if args.rate is not None else (1.0 if args.foxglove is not None else 0.0)
    return PlaybackConfig(rate=rate, wait_viewer_s=args.wait_viewer)


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


def _check_fleet_options(args: argparse.Namespace):
    """The replay's FleetConfig (None: no fleet); ConfigError for options that need one or clash."""
    from aefabmap.cli.run_config import fleet_config

    fleet = fleet_config(args)
    if fleet is None and (args.connect or args.listen or args.config or args.allow_exposure):
        raise ConfigError("--connect/--listen/--config/--allow-exposure are for --fleet: a replay alone uses no network")
    if fleet is not None and args.check:
        raise ConfigError("--check compares the log's results with the own map's: it does not go with --fleet, "
                          "whose loops to other robots' places the log cannot have")
    return fleet


def _join_fleet(args: argparse.Namespace, detector, config, stack):
    """Open the session and join the fleet (closed by `stack`); the FleetNode wrapping detector."""
    from aefabmap.cli.run import fleet_session, warn_exposure
    from aefabmap_runtime.adapters.fleet import join_fleet
    from aefabmap_runtime.adapters.zenoh_transport import cli_session_config, open_session

    sc = fleet_session(cli_session_config("listen", connect=args.connect, listen=args.listen,
                                          config_file=args.config, allow_exposure=args.allow_exposure), config)
    warn_exposure(sc, log)
    session = stack.enter_context(open_session(sc))
    return stack.enter_context(join_fleet(session, detector, config))


def main(args: argparse.Namespace, stop: threading.Event | None = None) -> int:
    """stop: ends the replay between frames and the serving after it (set by SIGINT/SIGTERM)."""
    from aefabmap.cli.run import start_live_view
    from aefabmap.cli.run_config import logged_run_config
    from aefabmap.cli.state_options import open_state
    from aefabmap_runtime.adapters.bundle_reader import load_detector
    from aefabmap_runtime.adapters.log_set import log_files
    from aefabmap_runtime.adapters.mcap_log import (
        RUN_CONFIG_METADATA,
        McapLogConfig,
        read_log_metadata,
    )
    from aefabmap_runtime.adapters.node import stop_on_signals
    from aefabmap_runtime.adapters.replay import replay
    from aefabmap_runtime.adapters.ros_bag import is_ros_bag

    stop = stop if stop is not None else threading.Event()
    state_dir = view = None
    network = contextlib.ExitStack()
    try:
        playback = playback_config(args)
        fleet_config = _check_fleet_options(args)
        # Replay with the whole configuration of the logged run (a bag has none: the defaults).
        bag = len(args.log) == 1 and is_ros_bag(args.log[0])
        source = args.log[0] if bag else log_files(args.log)
        logged = {} if bag else read_log_metadata(source[0]).get(RUN_CONFIG_METADATA) or {}
        detector_config = logged_run_config(logged).detector
        # --foxglove draws the inlier matches (kept only then; they do not change any decision).
        detector_config = dataclasses.replace(detector_config, verification=dataclasses.replace(
            detector_config.verification, keep_inlier_points=args.foxglove is not None))
        detector = load_detector(args.model, detector_config)
        if args.state is not None:
            state_dir = open_state(args.state, detector, log)
        # A fleet node serves the places of a loaded state too: join once the map is there.
        fleet = _join_fleet(args, detector, fleet_config, network) if fleet_config is not None else None
        with stop_on_signals(stop):
            view = start_live_view(args)
            if playback.wait_viewer_s is not None:
                log.info("waiting up to %g s for a Foxglove viewer to subscribe", playback.wait_viewer_s)
            summary = replay(fleet if fleet is not None else detector, source, out_path=args.out, check=args.check,
                             image_topic=args.topic, view=view, playback=playback, stop=stop,
                             log_config=McapLogConfig(profile=args.mcap_profile))
            if state_dir is not None:
                info = state_dir.save(detector.state())
                log.info("map state saved to %s: %d places, %d bytes", info.path, info.n_places, info.nbytes)
                state_dir.close()
                state_dir = None
            code = report_summary(args, summary)
            if (view is not None or fleet is not None) and not stop.is_set():
                serve_until_stopped(view, fleet, stop)
        return code
    except AefabmapError as exc:
        log.error("%s", exc)
        return exc.exit_code
    finally:
        if view is not None:
            view.close()
        network.close()
        if state_dir is not None:
            state_dir.close()


def report_summary(args: argparse.Namespace, summary) -> int:
    """Log and print the replay's summary (one JSON line on stdout); the exit code it calls for."""
    if summary.stopped:
        log.warning("replay stopped after %d frames (Ctrl-C/SIGTERM)", summary.frames_read)
    log.info("%s", summary.status.describe())
    if summary.status.truncated:
        log.warning("%s", summary.status.describe())
    doc = summary.to_dict()
    print(json.dumps(doc, default=str))
    if summary.frames_processed == 0 and not summary.stopped:
        status = summary.status
        why = status.last_invalid or (f"{summary.frames_read} frames read, none usable" if summary.frames_read
                                      else "no image messages")
        log.error("%s: nothing replayed on %s: %s", args.log, status.image_topic or "any topic", why)
        return LogError.exit_code
    if summary.check is not None:
        (log.info if summary.check.ok else log.error)("%s", summary.check.describe())
        return 0 if summary.check.ok else 1
    return 0
