"""``aefabmap run``: the streaming loop-closure node (Zenoh in, JSON results out, MCAP log).

Results go to the sibling key ``lcd`` of the image key (``robot/camera/image`` ->
``robot/camera/lcd``), stats to ``robot/camera/lcd/stats``; see aefabmap.runtime.adapters.zenoh_transport.
"""

from __future__ import annotations

import argparse
import json
import logging
import threading

from aefabmap.errors import AefabmapError

log = logging.getLogger("aefabmap.run")


def add_zenoh_options(p: argparse.ArgumentParser, *, config: bool = True) -> None:
    """--connect / --listen (repeatable or comma-separated) and --config (zenoh JSON5 file)."""
    p.add_argument("--connect", action="append", metavar="EP", default=[],
                   help="zenoh endpoint to connect to, e.g. tcp/192.168.1.10:7447 (repeatable)")
    p.add_argument("--listen", action="append", metavar="EP", default=[],
                   help="zenoh endpoint to listen on, e.g. tcp/0.0.0.0:7447 (repeatable; exposes the node "
                   "to that network)")
    if config:
        p.add_argument("--config", metavar="zenoh.json5", default=None,
                       help="zenoh JSON5 configuration file (--connect/--listen override it)")
    p.epilog = ("Network: with none of --connect/--listen/--config, `run` listens on tcp/127.0.0.1:7447 only and "
                "`publish` connects there; no multicast scouting.")


def register(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "run",
        help="run the streaming loop-closure node",
        description="Subscribe to an image key, run FAB-MAP 2.0 on every frame, publish JSON results "
        "on the sibling key 'lcd' and log images, results and stats to MCAP. Stop with Ctrl-C/SIGTERM.",
    )
    p.add_argument("--model", required=True, metavar="BUNDLE", help="model bundle directory")
    p.add_argument("--key", required=True, metavar="KEYEXPR", help="zenoh image key, e.g. robot/camera/image")
    add_zenoh_options(p)
    p.add_argument("--mcap", required=True, metavar="LOG.mcap", help="MCAP log to write")
    p.add_argument("--max-places", type=int, default=None, metavar="N", help="cap on places in the map")
    p.add_argument("--memory-mb", type=float, default=None, metavar="MB", help="memory budget of the map (MB)")
    p.add_argument("--queue", type=int, default=2, metavar="N",
                   help="frames kept while busy; older ones are dropped (default 2)")
    p.add_argument("--image-every", type=int, default=1, metavar="N",
                   help="log every N-th image (default 1: exact replay possible; 0: no images)")
    from aefabmap.cli.state_options import add_state_options

    add_state_options(p, snapshots=True)
    p.set_defaults(func=main)
    return p


def main(args: argparse.Namespace) -> int:
    from aefabmap.runtime.adapters.bundle_reader import load_detector
    from aefabmap.runtime.adapters.node import NodeOptions, run_node, stop_on_signals
    from aefabmap.runtime.adapters.zenoh_transport import cli_session_config
    from aefabmap.runtime.core.detector import DetectorConfig

    stop = threading.Event()
    state_dir = snapshotter = None
    try:
        session = cli_session_config("listen", connect=args.connect, listen=args.listen, config_file=args.config)
        detector = load_detector(args.model, DetectorConfig(max_places=args.max_places, memory_mb=args.memory_mb))
        run_config = {"model": str(args.model), "max_places": args.max_places, "memory_mb": args.memory_mb}

        options = NodeOptions(key=args.key, mcap_path=args.mcap, session=session, queue_size=args.queue,
                              stats_period_s=5.0, image_log_every=args.image_every, run_config=run_config)

        def on_stats(msg) -> None:
            log.info(
                "processed %d, dropped %d, bad %d, loops %d, %s fps, latency p50 %s ms p95 %s ms, RSS %s MB",
                msg.frames_processed, msg.dropped, msg.bad_total, msg.loops, _fmt(msg.fps),
                _fmt(msg.latency_ms.p50), _fmt(msg.latency_ms.p95), msg.rss_mb,
            )

        if getattr(args, "state", None) is not None:
            from aefabmap.cli.state_options import open_state
            from aefabmap.runtime.adapters.map_state import SnapshotPolicy, Snapshotter

            policy = SnapshotPolicy.parse(args.snapshot_every)
            state_dir = open_state(args.state, detector, log)
            snapshotter = Snapshotter(
                detector, state_dir, policy,
                on_error=lambda exc: log.warning("snapshot failed, the previous one is kept: %s", exc),
                on_saved=lambda info: log.debug("snapshot %s: %d places, %d bytes, %.3f s",
                                                info.path.name, info.n_places, info.nbytes, info.seconds),
                background=True,
            )

        with stop_on_signals(stop):
            summary = run_node(detector, options, stop_event=stop, on_stats=on_stats, snapshotter=snapshotter)
        if snapshotter is not None and snapshotter.saved:
            last = snapshotter.saved[-1]
            log.info("map state saved to %s: %d places, %d bytes", last.path, last.n_places, last.nbytes)
    except AefabmapError as exc:
        log.error("%s", exc)
        return exc.exit_code
    finally:
        if snapshotter is not None:
            snapshotter.join()  # a snapshot being written when the run failed
        if state_dir is not None:
            state_dir.close()
    print(json.dumps(summary.to_dict()))
    return 0


def _fmt(v) -> str:
    return "-" if v is None else f"{v:.1f}"
