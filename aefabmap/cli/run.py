"""``aefabmap run``: the streaming loop-closure node (Zenoh in, JSON results out, MCAP log).

Results go to the sibling key ``lcd`` of the image key (``robot/camera/image`` ->
``robot/camera/lcd``), stats to ``robot/camera/lcd/stats``; see aefabmap_runtime.adapters.zenoh_transport.
The node is built and run by aefabmap_runtime.adapters.node_builder; this module reads the options.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import threading

from aefabmap.cli.options import (
    add_detector_options,
    add_fleet_options,
    add_foxglove_options,
    add_log_rotation_options,
    add_mcap_profile_option,
    add_state_options,
    add_workers_option,
    add_zenoh_options,
    build_run_config,
    endpoints,
    log_rotation_config,
)
from aefabmap_runtime.errors import AefabmapError, ConfigError

log = logging.getLogger("aefabmap.run")


def register(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "run",
        help="run the streaming loop-closure node",
        description="Subscribe to an image key, run FAB-MAP 2.0 on every frame, publish JSON results "
        "on the sibling key 'lcd' and log images, results and stats to MCAP. Stop with Ctrl-C/SIGTERM.",
    )
    model = p.add_argument_group("model and processing")
    model.add_argument("--model", required=True, metavar="BUNDLE", help="model bundle directory")
    inp = p.add_argument_group("input and output (Zenoh or ROS 2)")
    inp.add_argument("--key", default=None, metavar="KEYEXPR", help="zenoh image key, e.g. robot/camera/image")
    inp.add_argument("--ros-topic", default=None, metavar="TOPIC",
                   help="instead of --key: ROS 2 image topic (sensor_msgs Image or CompressedImage) read over "
                   "rmw_zenoh (or zenoh-bridge-ros2dds: --ros-bridge), e.g. /camera/image_raw; results also go to "
                   "the ROS 2 topic /lcd/result (std_msgs/String JSON). Connects to the rmw_zenoh router (or the "
                   "bridge) tcp/127.0.0.1:7447 by default. A topic nobody publishes is warned about 3 s after "
                   "start, with the image topics that are")
    inp.add_argument("--ros-bridge", nargs="?", const="/", default=None, metavar="NS",
                     help="with --ros-topic: for ROS 2 on DDS (Fast DDS, Cyclone DDS), read the topic through "
                     "zenoh-bridge-ros2dds instead of rmw_zenoh (key camera/image_raw for /camera/image_raw); NS: "
                     "the namespace the bridge was given (its -n/--namespace; default /: none)")
    inp.add_argument("--ros-domain", type=int, default=None, metavar="ID",
                     help="ROS 2 domain id (default: $ROS_DOMAIN_ID, as ROS 2 tools read it, else 0; with "
                     "--ros-bridge, the bridge's own setting: not given here)")
    inp.add_argument("--ros-distro", choices=("auto", "humble", "jazzy"), default=None,
                   help="type hashes of the published ROS 2 topics: auto (default: the camera's, read from its "
                   "first image sample), humble (none) or jazzy (RIHS01; also iron, kilted, rolling); not with "
                   "--ros-bridge, whose keys have none")
    inp.add_argument("--ros-namespace", default="/", metavar="NS",
                     help="ROS 2 namespace of the node (default /): relative result/stats topics go under it")
    inp.add_argument("--ros-node-name", default="aefabmap", metavar="NAME",
                     help="ROS 2 node name (default aefabmap; through --ros-bridge, only the diagnostics' name)")
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
                   "a directory (an existing one, or DIR/ ending in a separator: created with its parents when missing; files "
                   "lcd-YYYYmmdd-HHMMSS-0001.mcap) or a pattern with {n} (run-{n}.mcap)")
    add_log_rotation_options(logs)
    add_mcap_profile_option(logs)
    inp.add_argument("--queue", type=int, default=None, metavar="N",
                   help="frames kept while busy; older ones are dropped (default 2, or the profile's)")
    logs.add_argument("--image-every", type=int, default=1, metavar="N",
                   help="log every N-th image (default 1: exact replay possible; 0: no images)")
    add_workers_option(model)
    add_detector_options(p, profile=True)
    add_fleet_options(p)
    add_state_options(p.add_argument_group("map state (kept between runs)"), snapshots=True)
    add_foxglove_options(p.add_argument_group("live view (Foxglove)"))
    p.set_defaults(func=main)
    return p


def main(args: argparse.Namespace) -> int:
    from aefabmap_runtime.adapters.node_builder import run_configured_node

    try:
        io = node_io(args)
        # The live view draws the inlier matches: keep them (a few hundred floats a frame).
        config = build_run_config(args, keep_inlier_points=args.foxglove is not None)
        run = run_configured_node(config, io, stop_event=threading.Event())
    except AefabmapError as exc:
        log.error("%s", exc)
        return exc.exit_code
    print(json.dumps(run.to_dict()))
    return 0


def node_io(args: argparse.Namespace):
    """The node_builder.NodeIO of the parsed options (ConfigError when they clash)."""
    from aefabmap_runtime.adapters.node_builder import NodeIO
    from aefabmap_runtime.adapters.state_dir import SnapshotPolicy

    if (args.key is None) == (args.ros_topic is None):
        raise ConfigError("give exactly one of --key (zenoh image key) and --ros-topic (ROS 2 image topic)")
    if args.ros_bridge is not None and args.ros_topic is None:
        raise ConfigError("--ros-bridge reads a ROS 2 topic: give --ros-topic with it")
    ros = _ros_options(args) if args.ros_topic is not None else None
    rotation = log_rotation_config(args)
    snapshots = SnapshotPolicy.parse(args.snapshot_every) if args.state is not None else SnapshotPolicy()
    return NodeIO(mcap=args.mcap, key=args.key, ros=ros, results_key=args.results_key,
                  endpoints=endpoints(args), log_rotation=rotation, mcap_profile=args.mcap_profile,
                  image_every=args.image_every, state=args.state, snapshots=snapshots,
                  foxglove_port=args.foxglove, foxglove_host=args.foxglove_host)


def _ros_options(args: argparse.Namespace):
    """The RosOptions of --ros-topic and its siblings (the domain: --ros-domain, else $ROS_DOMAIN_ID;
    through --ros-bridge neither domain nor distribution, which the bridge's keys do not carry)."""
    from aefabmap_runtime.adapters.rmw_zenoh import RosOptions, domain_from_env

    names = dict(topic=args.ros_topic, namespace=args.ros_namespace, node=args.ros_node_name,
                 result_topic=args.ros_result_topic, stats_topic=args.ros_stats_topic)
    if args.ros_bridge is not None:
        for flag, value, why in (
                ("--ros-domain", args.ros_domain, "the bridge serves one DDS domain: set it there (its -d)"),
                ("--ros-distro", args.ros_distro, "zenoh-bridge-ros2dds's keys carry no type hash")):
            if value is not None:
                raise ConfigError(f"{flag} means nothing with --ros-bridge: {why}")
        return RosOptions(bridge=args.ros_bridge, **names)
    domain = args.ros_domain if args.ros_domain is not None else domain_from_env(os.environ)
    return RosOptions(domain=domain, distro=args.ros_distro or "auto", **names)
