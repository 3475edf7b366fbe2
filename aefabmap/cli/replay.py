"""``aefabmap replay``: run a bundle over the images of an MCAP log (own log or ROS 2 bag).

Exit code: 0, or 1 when ``--check`` finds results that differ from the logged ones;
errors exit with the code of their aefabmap.errors class.
"""

from __future__ import annotations

import argparse
import json
import logging

from aefabmap.errors import AefabmapError

log = logging.getLogger("aefabmap.replay")


def register(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "replay",
        help="replay an MCAP log (or ROS 2 bag) through a model bundle",
        description="Run the detector over the logged images; optionally write a new log (--out) and "
        "compare with the logged results (--check; deterministic fields only, not timings).",
    )
    p.add_argument("log", metavar="LOG.mcap", nargs="+",
                   help="aefabmap MCAP log or ROS 2 bag (.mcap); several files, a directory of rotated files or a "
                   "glob are read in run order as one run")
    p.add_argument("--model", required=True, metavar="BUNDLE", help="model bundle directory")
    p.add_argument("--out", default=None, metavar="NEW.mcap", help="write the replayed run to this MCAP")
    p.add_argument("--check", action="store_true", help="compare with the results in the log")
    p.set_defaults(func=main)
    return p


def main(args: argparse.Namespace) -> int:
    from aefabmap.runtime.adapters.bundle_reader import load_detector
    from aefabmap.runtime.adapters.log_set import log_files
    from aefabmap.runtime.adapters.mcap_log import (
        RUN_CONFIG_METADATA,
        read_log_metadata,
    )
    from aefabmap.runtime.adapters.replay import replay
    from aefabmap.runtime.core.detector import DetectorConfig

    try:
        # Replay with the detector options of the logged run (max places, memory budget).
        files = log_files(args.log)
        logged = read_log_metadata(files[0]).get(RUN_CONFIG_METADATA) or {}
        detector = load_detector(
            args.model, DetectorConfig(max_places=logged.get("max_places"), memory_mb=logged.get("memory_mb"))
        )
        summary = replay(detector, files, out_path=args.out, check=args.check)
    except AefabmapError as exc:
        log.error("%s", exc)
        return exc.exit_code
    log.info("%s", summary.status.describe())
    if summary.status.truncated:
        log.warning("%s", summary.status.describe())
    doc = summary.to_dict()
    print(json.dumps(doc, default=str))
    if summary.check is not None:
        (log.info if summary.check.ok else log.error)("%s", summary.check.describe())
        return 0 if summary.check.ok else 1
    return 0
