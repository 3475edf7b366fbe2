"""``aefabmap run``: the streaming loop-closure node (Zenoh in, JSON results out, MCAP log).

Results go to the sibling key ``lcd`` of the image key (``robot/camera/image`` ->
``robot/camera/lcd``), stats to ``robot/camera/lcd/stats``; see aefabmap_runtime.adapters.zenoh_transport.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import os
import threading

from aefabmap.cli.run_config import (
    RUN_CONFIG_KEY,
    add_detector_options,
    apply_process_settings,
    build_run_config,
)
from aefabmap_runtime.errors import AefabmapError, ConfigError
from aefabmap_runtime.core.profiles import get_profile

log = logging.getLogger("aefabmap.run")


def add_zenoh_options(p: argparse.ArgumentParser, group=None, *, config: bool = True) -> None:
    """--connect / --listen (repeatable or comma-separated) and --config (zenoh JSON5 file), in
    `group` (an argument group of p) when given; the network note goes to p's epilog."""
    g = group if group is not None else p
    g.add_argument("--connect", action="append", metavar="EP", default=[],
                   help="zenoh endpoint to connect to, e.g. tcp/192.168.1.10:7447 (repeatable)")
    g.add_argument("--listen", action="append", metavar="EP", default=[],
                   help="zenoh endpoint to listen on, e.g. tcp/192.168.1.20:7447 (repeatable; a non-loopback "
                   "endpoint without mutual TLS needs --allow-exposure)")
    g.add_argument("--allow-exposure", action="store_true",
                   help="accept a session other hosts reach without authentication (a non-loopback listen "
                   "endpoint without mutual TLS, or multicast scouting), from --listen or --config; logged at start")
    if config:
        g.add_argument("--config", metavar="zenoh.json5", default=None,
                       help="zenoh JSON5 configuration file (--connect/--listen override it)")
    p.epilog = ("Network: with none of --connect/--listen/--config, `run` listens on tcp/127.0.0.1:7447 only and "
                "`publish` connects there; no multicast scouting.")


def warn_exposure(session, logger: logging.Logger) -> None:
    """Log, at start, how a session accepted with --allow-exposure is exposed."""
    from aefabmap_runtime.adapters.zenoh_transport import session_exposure

    if session.allow_exposure:
        reasons = session_exposure(session)
        if reasons:
            logger.warning("network exposure accepted (--allow-exposure): the node %s", "; ".join(reasons))


def add_log_rotation_options(p: argparse.ArgumentParser) -> None:
    """--mcap-max-mb, --log-budget-mb and the free-space thresholds (rotating_log.LogRotationConfig)."""
    p.add_argument("--mcap-max-mb", type=float, default=None, metavar="MB",
                   help="start a new log file before the current one passes MB (default: one file)")
    p.add_argument("--log-budget-mb", type=float, default=None, metavar="MB",
                   help="delete the oldest closed files of the log set to keep it within MB (default: no limit)")
    p.add_argument("--log-min-free-mb", type=float, nargs=2, default=None, metavar=("IMAGES", "RESULTS"),
                   help="stop logging images below IMAGES MB free on the log's disk, everything below RESULTS "
                   "(default: max(500, 2 x --mcap-max-mb) and 100)")


def add_mcap_profile_option(p: argparse.ArgumentParser) -> None:
    """--mcap-profile: the layout of the written log (mcap_log.McapLogConfig.profile)."""
    p.add_argument("--mcap-profile", choices=("aefabmap", "ros2"), default="aefabmap",
                   help="layout of the MCAP log: aefabmap (default: protobuf image, JSON results) or ros2 (CDR "
                   "sensor_msgs/CompressedImage on /camera/image/compressed, std_msgs/String JSON results and stats; "
                   "ros2 bag play, rosbags and Foxglove read it, replay too)")


def log_rotation_config(args: argparse.Namespace):
    """The LogRotationConfig of the parsed options (ConfigError when inconsistent)."""
    from aefabmap_runtime.adapters.rotating_log import LogRotationConfig

    min_free = args.log_min_free_mb
    free = {} if min_free is None else {"images_min_free_mb": min_free[0], "results_min_free_mb": min_free[1]}
    return LogRotationConfig(max_mb=args.mcap_max_mb, budget_mb=args.log_budget_mb, **free)


def add_foxglove_options(p: argparse.ArgumentParser) -> None:
    """--foxglove [PORT] and --foxglove-host: the live view (runtime/aefabmap_runtime/adapters/foxglove_view.py)."""
    p.add_argument("--foxglove", type=int, nargs="?", const=8765, default=None, metavar="PORT",
                   help="serve a live view over the Foxglove WebSocket protocol on PORT (default 8765; 0: any free "
                   "port): camera image, inlier matches, matched place, result and stats plots (layout: "
                   "deploy/foxglove_layout.json; needs aefabmap[foxglove])")
    p.add_argument("--foxglove-host", default="127.0.0.1", metavar="HOST",
                   help="address the Foxglove server binds (default 127.0.0.1: this machine only; the protocol "
                   "has no authentication)")


def start_live_view(args: argparse.Namespace):
    """The LiveView of the parsed options (None without --foxglove); ConfigError without foxglove-sdk."""
    port = args.foxglove
    if port is None:
        return None
    from aefabmap_runtime.adapters.foxglove_view import FoxgloveServer, LiveView

    server = FoxgloveServer(port=port, host=args.foxglove_host)
    log.info("Foxglove live view on ws://%s:%d", server.host, server.port)
    return LiveView(server)


def fleet_session(session, fleet):
    """The session a fleet node opens: one that only connects (no listen endpoint, no config file,
    no mode given) joins as a Zenoh client, since peers behind a router exchange nothing unless
    each listens where the others reach it (docs/fleet.md)."""
    if fleet is None or session.mode is not None or session.config_file or session.listen or not session.connect:
        return session
    log.info("fleet %s: no listen endpoint: joining through %s as a Zenoh client", fleet.name,
             ", ".join(session.connect))
    return dataclasses.replace(session, mode="client")


def add_fleet_options(p: argparse.ArgumentParser):
    """--fleet, --robot and --fleet-timeout-ms (run_config.fleet_config reads them); returns their group."""
    fl = p.add_argument_group("fleet (robots that recognise each other's places)")
    fl.add_argument("--fleet", default=None, metavar="NAME",
                    help="join this fleet: offer this map's places to the other robots of the same bundle and "
                    "verify loops to theirs (a token: letters, digits, '_', '-')")
    fl.add_argument("--robot", default=None, metavar="ID", help="this robot's id in the fleet (same rules)")
    fl.add_argument("--fleet-timeout-ms", type=int, default=None, metavar="MS",
                    help="how long a fetch of another robot's keypoints may wait (default 300)")
    return fl


def register(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "run",
        help="run the streaming loop-closure node",
        description="Subscribe to an image key, run FAB-MAP 2.0 on every frame, publish JSON results "
        "on the sibling key 'lcd' and log images, results and stats to MCAP. Stop with Ctrl-C/SIGTERM.",
    )
    p.add_argument("--model", required=True, metavar="BUNDLE", help="model bundle directory")
    inp = p.add_argument_group("input and output (Zenoh or ROS 2)")
    inp.add_argument("--key", default=None, metavar="KEYEXPR", help="zenoh image key, e.g. robot/camera/image")
    inp.add_argument("--ros-topic", default=None, metavar="TOPIC",
                   help="instead of --key: ROS 2 image topic (sensor_msgs Image or CompressedImage) read over "
                   "rmw_zenoh, e.g. /camera/image_raw; results also go to the ROS 2 topic /lcd/result "
                   "(std_msgs/String JSON). Connects to the rmw_zenoh router tcp/127.0.0.1:7447 by default")
    inp.add_argument("--ros-domain", type=int, default=None, metavar="ID",
                     help="ROS 2 domain id (default: $ROS_DOMAIN_ID, as ROS 2 tools read it, else 0)")
    inp.add_argument("--ros-distro", choices=("auto", "humble", "jazzy"), default="auto",
                   help="type hashes of the published ROS 2 topics: auto (default: the camera's, read from its "
                   "first image sample), humble (none) or jazzy (RIHS01; also iron, kilted, rolling)")
    inp.add_argument("--ros-namespace", default="/", metavar="NS",
                     help="ROS 2 namespace of the node (default /): relative result/stats topics go under it")
    inp.add_argument("--ros-node-name", default="aefabmap", metavar="NAME", help="ROS 2 node name (default aefabmap)")
    inp.add_argument("--ros-result-topic", default="lcd/result", metavar="TOPIC",
                     help="ROS 2 topic of the results (default lcd/result, in the namespace)")
    inp.add_argument("--ros-stats-topic", default="lcd/stats", metavar="TOPIC",
                     help="ROS 2 topic of the stats (default lcd/stats, in the namespace)")
    inp.add_argument("--results-key", default=None, metavar="KEYEXPR",
                   help="zenoh key of the JSON results (stats on <key>/stats); default: the sibling 'lcd' of "
                   "the image key or topic")
    add_zenoh_options(p, inp)
    logs = p.add_argument_group("logging")
    logs.add_argument("--mcap", required=True, metavar="LOG.mcap|DIR/|PATTERN",
                   help="MCAP log to write: a file (an existing one is never overwritten: the next is LOG-0001.mcap), "
                   "a directory (files lcd-YYYYmmdd-HHMMSS-0001.mcap) or a pattern with {n} (run-{n}.mcap)")
    add_log_rotation_options(logs)
    add_mcap_profile_option(logs)
    inp.add_argument("--queue", type=int, default=None, metavar="N",
                   help="frames kept while busy; older ones are dropped (default 2, or the profile's)")
    logs.add_argument("--image-every", type=int, default=1, metavar="N",
                   help="log every N-th image (default 1: exact replay possible; 0: no images)")
    add_detector_options(p, profile=True)
    add_fleet_options(p)
    from aefabmap.cli.state_options import add_state_options

    add_state_options(p, snapshots=True)
    add_foxglove_options(p)
    p.set_defaults(func=main)
    return p


def main(args: argparse.Namespace) -> int:
    from pathlib import Path

    from aefabmap_runtime.adapters.bundle_reader import load_detector, read_manifest
    from aefabmap_runtime.adapters.mcap_log import McapLogConfig
    from aefabmap_runtime.adapters.node import NodeOptions, run_node, stop_on_signals
    from aefabmap_runtime.adapters.rmw_zenoh import ROS_PEER_LISTEN, RosOptions, domain_from_env
    from aefabmap_runtime.adapters.zenoh_transport import cli_session_config

    stop = threading.Event()
    state_dir = snapshotter = journal = view = state_report = None
    try:
        ros_topic = args.ros_topic
        if (args.key is None) == (ros_topic is None):
            raise ConfigError("give exactly one of --key (zenoh image key) and --ros-topic (ROS 2 image topic)")
        ros = None
        if ros_topic is not None:
            domain = args.ros_domain if args.ros_domain is not None else domain_from_env(os.environ)
            ros = RosOptions(topic=ros_topic, domain=domain, distro=args.ros_distro, namespace=args.ros_namespace,
                             node=args.ros_node_name, result_topic=args.ros_result_topic,
                             stats_topic=args.ros_stats_topic)
        rotation = log_rotation_config(args)
        # A ROS 2 run joins the rmw_zenoh router (it owns port 7447) instead of listening there.
        session = cli_session_config("connect" if ros is not None else "listen", connect=args.connect,
                                     listen=args.listen, config_file=args.config, allow_exposure=args.allow_exposure)
        if ros is not None and not args.config and not args.listen:
            # A peer of rmw_zenoh's graph on this host (router reachable, listening on loopback only).
            session = dataclasses.replace(session, mode="peer", listen=(ROS_PEER_LISTEN,))
        warn_exposure(session, log)
        # The live view draws the inlier matches: keep them (a few hundred floats a frame).
        config = build_run_config(args, keep_inlier_points=args.foxglove is not None)
        session = fleet_session(session, config.fleet)
        if config.profile is not None:  # before loading: the profile's model or nothing
            get_profile(config.profile).check_bundle(read_manifest(Path(args.model)))
        apply_process_settings(config)
        detector = load_detector(args.model, config.detector)

        def on_stats(msg) -> None:
            log.info(
                "processed %d, dropped %d, bad %d, loops %d, %s fps, latency p50 %s ms p95 %s ms, RSS %s MB, "
                "log %s (%d errors)",
                msg.frames_processed, msg.dropped, msg.bad_total, msg.loops, _fmt(msg.fps),
                _fmt(msg.latency_ms.p50), _fmt(msg.latency_ms.p95), msg.rss_mb, msg.log_state, msg.log_errors,
            )
            if journal is not None and journal.behind:  # frames the map state could not keep so far
                log.warning("%s", journal.report().line())

        if args.state is not None:
            from aefabmap.cli.state_options import open_state
            from aefabmap_runtime.adapters.map_journal import MapJournal
            from aefabmap_runtime.adapters.state_dir import SnapshotPolicy, Snapshotter

            policy = SnapshotPolicy.parse(args.snapshot_every)
            state_dir = open_state(args.state, detector, log)
            # Every frame between snapshots goes to the journal: a failing disk loses only what it could not take.
            journal = MapJournal(state_dir, detector, on_error=lambda exc: log.warning("%s", exc))
            snapshotter = Snapshotter(
                detector, state_dir, policy,
                on_error=lambda exc: log.warning("snapshot failed, the previous one is kept: %s", exc),
                on_saved=lambda info: log.debug("snapshot %s: %d places, %d bytes, %.3f s",
                                                info.path.name, info.n_places, info.nbytes, info.seconds),
                background=True, journal=journal,
            )

        # The map this run starts from (a loaded state's frame counter, 0: empty), so that a replay of
        # a log set spanning restarts rebuilds each run's map (runtime/aefabmap_runtime/adapters/replay.py).
        map_start = {"frame": getattr(detector, "next_sequence", 0), "places": getattr(detector, "n_places", 0)}
        options = NodeOptions(key=args.key if ros is None else ros.image_key, mcap_path=args.mcap, session=session,
                              queue_size=config.queue, stats_period_s=5.0, image_log_every=args.image_every,
                              run_config={RUN_CONFIG_KEY: config.to_dict(), "map_start": map_start},
                              result_key=args.results_key, ros=ros, log_rotation=rotation,
                              log_config=McapLogConfig(profile=args.mcap_profile), fleet=config.fleet)
        from aefabmap_runtime.core.kernels import compiled

        log.info("kernels: %s", compiled.describe())  # once the run's settings and state are accepted
        view = start_live_view(args)
        with stop_on_signals(stop):
            summary = run_node(detector, options, stop_event=stop, on_stats=on_stats, snapshotter=snapshotter,
                               view=view)
        if snapshotter is not None and snapshotter.saved:
            last = snapshotter.saved[-1]
            log.info("map state saved to %s: %d places, %d bytes", last.path, last.n_places, last.nbytes)
        if journal is not None:
            journal.close()
            state_report = journal.report()
            (log.warning if state_report.frames_not_written else log.info)("%s", state_report.line())
    except AefabmapError as exc:
        log.error("%s", exc)
        return exc.exit_code
    finally:
        if view is not None:
            view.close()
        if snapshotter is not None:
            snapshotter.join()  # a snapshot being written when the run failed
        if journal is not None:
            journal.close()
        if state_dir is not None:
            state_dir.close()
    doc = summary.to_dict()
    if state_report is not None:
        doc["state"] = state_report.to_dict()
    print(json.dumps(doc))
    return 0


def _fmt(v) -> str:
    return "-" if v is None else f"{v:.1f}"
