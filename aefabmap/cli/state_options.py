"""``--state DIR`` of run, replay and eval: where the map is kept between runs
(runtime/adapters/map_state.py)."""

from __future__ import annotations

import argparse
import logging


def add_state_options(p: argparse.ArgumentParser, *, snapshots: bool = False) -> None:
    """--state DIR (and, for the live node, --snapshot-every)."""
    p.add_argument("--state", default=None, metavar="DIR",
                   help="keep the map in DIR: loaded at start when present, saved at the end"
                   + (" and every --snapshot-every" if snapshots else ""))
    if snapshots:
        p.add_argument("--snapshot-every", default="60s", metavar="N{s,m,p}",
                       help="with --state: snapshot every N seconds (60s), minutes (5m) or new places (100p); "
                       "default 60s. A kill -9 loses at most the frames since the last snapshot")


def open_state(path, detector, logger: logging.Logger):
    """Open (lock) the state directory DIR for ``detector``'s bundle and load its map if present."""
    from aefabmap.runtime.adapters.map_state import MapStateDir, bundle_id, load_into

    directory = MapStateDir(path, bundle_id(detector.manifest)).open()
    try:
        if load_into(detector, directory):
            logger.info("map state %s loaded: %d places, next frame %d", path, detector.n_places, detector.next_sequence)
    except BaseException:
        directory.close()
        raise
    return directory
