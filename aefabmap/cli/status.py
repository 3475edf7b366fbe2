"""``aefabmap status``: find the running nodes (Zenoh liveliness) and print each one's health.

Exit codes: 0 when at least one node answered and none reports a warning (a ROS 2 topic nobody
publishes, results no ROS 2 subscriber can read), 1 when none was found, none answered or one warns
(each warning is printed under its node's line), 5 on a transport error
(runtime/aefabmap_runtime/adapters/health.py for the keys).
"""

from __future__ import annotations

import argparse
import json
import logging
import threading
import time

log = logging.getLogger("aefabmap.status")


def register(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "status",
        help="list the running aefabmap nodes and their health",
        description="Find every running node by its liveliness token (aefabmap/runtime/<zid>) and query its status.",
        epilog="Here exit code 1 means that no node was found, none answered or one reports a warning.",
    )
    p.add_argument("--connect", action="append", metavar="EP", default=[],
                   help="zenoh endpoint to connect to (repeatable; default tcp/127.0.0.1:7447)")
    p.add_argument("--timeout", type=float, default=3.0, metavar="S",
                   help="seconds to wait for the connection, the token list and the answers (default 3)")
    p.add_argument("--json", action="store_true", help="print one JSON list of the status messages")
    p.set_defaults(func=main)
    return p


def _line(zid: str, st) -> str:
    if isinstance(st, str):
        return f"{zid}  no status: {st}"
    stages = " ".join(f"{k}={v:.1f}" for k, v in sorted(st.stage_ms.items()))
    mb = "?" if st.rss_mb is None else f"{st.rss_mb:.0f}"
    map_mb = "?" if st.map_mb is None else f"{st.map_mb:.1f}"
    return (f"{zid}  {st.results_key}  up {st.uptime_s:.0f}s  frames {st.frames_processed}/{st.frames_received}  "
            f"drops {st.dropped}  bad {st.bad_total}  places {st.places if st.places is not None else '?'}  "
            f"map {map_mb} MB  rss {mb} MB  log {st.log_files} files {st.log_bytes / 2**20:.1f} MB "
            f"({st.log_state})  bundle {(st.bundle_id or '?')[:12]}  v{st.aefabmap_version}"
            + (f"  ms: {stages}" if stages else "")
            + "".join(f"\n{zid}  warning: {w}" for w in st.warnings))


def main(args: argparse.Namespace) -> int:
    from aefabmap_runtime.errors import ConfigError
    from aefabmap_runtime.adapters.health import (
        find_runtimes,
        query_status,
        wait_for_peer,
    )
    from aefabmap_runtime.adapters.zenoh_transport import (
        cli_session_config,
        open_session,
    )

    if not args.timeout > 0:
        raise ConfigError(f"--timeout must be > 0 s, got {args.timeout}")
    config = cli_session_config("connect", connect=args.connect)
    where = ", ".join(config.connect)
    deadline = time.monotonic() + args.timeout
    session = open_session(config)
    try:
        zids = []
        if wait_for_peer(session, args.timeout):
            zids = find_runtimes(session, max(0.2, deadline - time.monotonic()))
            pause = threading.Event()
            # A peer also links to the peers a router tells it of (a ROS 2 node behind rmw_zenoh's
            # router): a query sent while those links come up can miss the node, so ask again.
            while not zids and time.monotonic() + 0.1 < deadline:
                pause.wait(0.1)
                zids = find_runtimes(session, max(0.2, deadline - time.monotonic()))
        answers = query_status(session, zids, max(0.5, deadline - time.monotonic())) if zids else {}
    finally:
        session.close()
    if not zids:
        print(f"no aefabmap runtime found on {where}")
        return 1
    if args.json:
        print(json.dumps([st.to_dict() if not isinstance(st, str) else {"zid": zid, "error": st}
                          for zid, st in answers.items()]))
    else:
        for zid, st in answers.items():
            print(_line(zid, st))
    answered = [st for st in answers.values() if not isinstance(st, str)]
    return 0 if answered and not any(st.warnings for st in answered) else 1
