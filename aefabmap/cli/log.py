"""``aefabmap log``: tools for MCAP logs. ``log repair`` makes a cut-off log readable by standard readers."""

from __future__ import annotations

import argparse
import json
import logging

log = logging.getLogger("aefabmap.log")


def register(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser("log", help="tools for MCAP logs (repair a cut-off log)",
                              description="Tools for the MCAP logs `run` and `replay --out` write.")
    sub = p.add_subparsers(dest="log_command", required=True)
    r = sub.add_parser("repair", help="copy a cut-off log (full disk, kill -9) into a finished one",
                       description="Read LOG up to its last complete record and write every schema, channel, "
                       "metadata record and message into OUT, a finished MCAP file with a summary, so that readers "
                       "that seek (the mcap CLI, Foxglove, rosbags) read it. LOG is not changed.")
    r.add_argument("log", metavar="LOG", help="the cut-off MCAP file")
    r.add_argument("--out", required=True, metavar="OUT.mcap", help="the repaired file (must not exist yet)")
    r.set_defaults(func=repair)
    return p


def repair(args: argparse.Namespace) -> int:
    from aefabmap_runtime.adapters.log_repair import repair_log

    report = repair_log(args.log, args.out)
    state = f"cut off ({report.reason})" if report.truncated else "complete"
    log.info("%s was %s: %d messages on %d channels and %d metadata records written to %s",
             args.log, state, report.messages, report.channels, report.metadata, args.out)
    print(json.dumps(report.to_dict()))
    return 0
