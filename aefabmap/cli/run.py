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
                   help="zenoh endpoint to listen on, e.g. tcp/0.0.0.0:7447 (repeatable)")
    if config:
        p.add_argument("--config", metavar="zenoh.json5", default=None,
                       help="zenoh JSON5 configuration file (--connect/--listen override it)")


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
    p.add_argument("--camera", default=None, metavar="FX,FY,CX,CY",
                   help="pinhole intrinsics in pixels of the images: verify loops with an essential matrix")
    p.add_argument("--queue", type=int, default=2, metavar="N",
                   help="frames kept while busy; older ones are dropped (default 2)")
    p.add_argument("--image-every", type=int, default=1, metavar="N",
                   help="log every N-th image (default 1: exact replay possible; 0: no images)")
    p.set_defaults(func=main)
    return p


def main(args: argparse.Namespace) -> int:
    from aefabmap.runtime.adapters.bundle_reader import load_detector
    from aefabmap.runtime.adapters.node import run_node, stop_on_signals
    from aefabmap.runtime.adapters.zenoh_transport import SessionConfig
    from aefabmap.runtime.core.detector import DetectorConfig
    from aefabmap.runtime.core.verification import VerificationConfig

    stop = threading.Event()
    try:
        session = SessionConfig(connect=tuple(args.connect), listen=tuple(args.listen), config_file=args.config)
        verification = VerificationConfig(camera=getattr(args, "camera", None))
        detector = load_detector(args.model, DetectorConfig(max_places=args.max_places, memory_mb=args.memory_mb,
                                                            verification=verification))
        # `camera` as a list: VerificationConfig(camera=...) reads it back from this record.
        run_config = {"model": str(args.model), "max_places": args.max_places, "memory_mb": args.memory_mb,
                      "camera": list(verification.camera) if verification.camera else None}

        def on_stats(doc: dict) -> None:
            lat = doc.get("latency_ms") or {}
            log.info(
                "processed %d, dropped %d, bad %d, loops %d, %.1f fps, latency p50 %s ms p95 %s ms, RSS %s MB",
                doc["frames_processed"], doc["dropped"], doc["bad_total"], doc["loops"], doc["fps"],
                _fmt(lat.get("p50")), _fmt(lat.get("p95")), doc.get("rss_mb"),
            )

        with stop_on_signals(stop):
            summary = run_node(
                detector, session, args.key, args.mcap,
                queue_size=args.queue, stop_event=stop, stats_period_s=5.0,
                image_log_every=args.image_every, run_config=run_config, on_stats=on_stats,
            )
    except AefabmapError as exc:
        log.error("%s", exc)
        return exc.exit_code
    print(json.dumps(summary.to_dict()))
    return 0


def _fmt(v) -> str:
    return "-" if v is None else f"{v:.1f}"
