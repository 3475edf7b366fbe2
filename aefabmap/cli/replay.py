"""``aefabmap replay``: run a bundle over the images of an MCAP log (own log or ROS 2 bag).

Exit code: 0, or 1 when ``--check`` finds results that differ from the logged ones, or 130
(interrupted) when Ctrl-C/SIGTERM stopped it before the end of the log (while it waited for a
viewer, or during the replay; the summary is printed all the same); errors exit with the code of
their aefabmap_runtime.errors class. With ``--foxglove`` the replay plays at
the recorded pace (``--rate``), optionally after the first viewer (``--wait-viewer``), and the
server stays up after it until Ctrl-C/SIGTERM (docs/streaming.md, "Replay in Foxglove"). With
``--fleet NAME --robot ID`` the replay joins a fleet as `run` does (docs/fleet.md): the map it
builds from the log is offered to the other robots, during the replay and after it until
Ctrl-C/SIGTERM.
"""

from __future__ import annotations

import argparse
import json
import logging
import threading

from aefabmap.cli.options import (
    add_fleet_options,
    add_foxglove_options,
    add_workers_option,
    add_mcap_profile_option,
    add_state_options,
    add_zenoh_options,
    endpoints,
    fleet_config,
)
from aefabmap_runtime.core.run_config import check_workers
from aefabmap_runtime.errors import AefabmapError, ConfigError, LogError

log = logging.getLogger("aefabmap.replay")


def register(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "replay",
        help="replay an MCAP log (or ROS 2 bag) through a model bundle",
        description="Run the detector over the logged images; optionally write a new log (--out) and "
        "compare with the logged results (--check; deterministic fields only, not timings).",
    )
    src = p.add_argument_group("input")
    src.add_argument("log", metavar="LOG", nargs="+",
                     help="aefabmap MCAP log (several files, a directory of rotated files or a glob are read in run "
                     "order as one run), or a ROS bag: rosbag2 directory (metadata.yaml), .db3 or .mcap file, "
                     "ROS 1 .bag (needs aefabmap[ros], except ROS 2 .mcap)")
    src.add_argument("--topic", default=None, metavar="TOPIC",
                     help="image topic to replay (required when the bag has several image topics)")
    model = p.add_argument_group("model and processing")
    model.add_argument("--model", required=True, metavar="BUNDLE", help="model bundle directory")
    add_workers_option(model)
    out = p.add_argument_group("output and check")
    out.add_argument("--out", default=None, metavar="NEW.mcap", help="write the replayed run to this MCAP")
    out.add_argument("--check", action="store_true", help="compare with the results in the log")
    add_mcap_profile_option(out)
    add_state_options(p.add_argument_group("map state (kept between runs)"))
    add_foxglove_options(p.add_argument_group("live view (Foxglove)"))
    add_playback_options(p.add_argument_group("playback"))
    add_zenoh_options(p, add_fleet_options(p))
    p.epilog = ("Network (--fleet only): with none of --connect/--listen/--config the replay listens on "
                "tcp/127.0.0.1:7447 only, as `run` does; no multicast scouting.")
    p.set_defaults(func=main)
    return p


#: Exit code of a replay stopped before the end of its log (Ctrl-C/SIGTERM), as main's for Ctrl-C.
EXIT_INTERRUPTED = 130
#: Longest wait (s) for a viewer when --wait-viewer is given without a value.
DEFAULT_WAIT_VIEWER_S = 120.0


def add_playback_options(p) -> None:
    """--rate and --wait-viewer (replay.PlaybackConfig), in p (a parser or argument group)."""
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


def _check_fleet_options(args: argparse.Namespace):
    """The replay's FleetConfig (None: no fleet); ConfigError for options that need one or clash."""
    fleet = fleet_config(args)
    if fleet is None and (args.connect or args.listen or args.config):
        raise ConfigError("--connect/--listen/--config are for --fleet: a replay alone uses no Zenoh network")
    if fleet is None and args.allow_exposure and args.foxglove is None:
        raise ConfigError("--allow-exposure is for --fleet or --foxglove: a replay alone uses no network")
    if fleet is not None and args.check:
        raise ConfigError("--check compares the log's results with the own map's: it does not go with --fleet, "
                          "whose loops to other robots' places the log cannot have")
    return fleet


def replay_io(args: argparse.Namespace):
    """The replay_builder.ReplayIO of the parsed options (ConfigError when they clash)."""
    from aefabmap_runtime.adapters.replay_builder import ReplayIO

    playback = playback_config(args)
    fleet = _check_fleet_options(args)
    return ReplayIO(logs=tuple(args.log), model=args.model, out=args.out, check=args.check, topic=args.topic,
                    mcap_profile=args.mcap_profile, state=args.state, foxglove_port=args.foxglove,
                    foxglove_host=args.foxglove_host, playback=playback, fleet=fleet, endpoints=endpoints(args),
                    workers=check_workers(args.workers if args.workers is not None else 1),
                    localize=bool(args.localize))


def main(args: argparse.Namespace, stop: threading.Event | None = None) -> int:
    """stop: ends the replay between frames and the serving after it (set by SIGINT/SIGTERM)."""
    from aefabmap_runtime.adapters.replay_builder import ConfiguredReplay

    stop = stop if stop is not None else threading.Event()
    try:
        with ConfiguredReplay(replay_io(args), stop) as replayer:
            code = report_summary(args, replayer.replay())
            replayer.serve_until_stopped()
        return code
    except AefabmapError as exc:
        log.error("%s", exc)
        return exc.exit_code


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
    code = 0
    if summary.check is not None:
        (log.info if summary.check.ok else log.error)("%s", summary.check.describe())
        code = 0 if summary.check.ok else 1
    return EXIT_INTERRUPTED if summary.stopped else code
