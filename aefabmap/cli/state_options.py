"""``--state DIR`` of run, replay and eval: where the map is kept between runs
(runtime/aefabmap_runtime/adapters/state_dir.py)."""

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
                       "default 60s. Frames between snapshots go to a journal in DIR: a kill -9 or a full disk loses only "
                       "the frames that could not be written")


def open_state(path, detector, logger: logging.Logger):
    """Open (lock) the state directory DIR for ``detector``'s bundle and load its map if present:
    the current snapshot, then the frames of its journal. A snapshot built with other detector
    settings loads (it continues with this run's), with a warning naming them; a journal must
    match them (runtime/aefabmap_runtime/adapters/map_journal.py)."""
    from aefabmap_runtime.adapters.state_dir import MapStateDir, bundle_id, load_map
    from aefabmap_runtime.core.run_config import recorded_settings_differences

    directory = MapStateDir(path, bundle_id(detector.manifest)).open()
    try:
        state, journal = load_map(detector, directory)
        _log_journal(journal, path, logger)
        if state is not None or journal.frames:
            logger.info("map state %s loaded: %d places, next frame %d", path, detector.n_places, detector.next_sequence)
            stored = state.scalars.get("config") if state is not None else None
            if isinstance(stored, str):
                differ = recorded_settings_differences(stored, detector.config)
                if differ:
                    logger.warning("map state %s was built with other detector settings (%s); this run continues "
                                   "it with its own", path, ", ".join(differ))
    except BaseException:
        directory.close()
        raise
    return directory


def _log_journal(journal, path, logger: logging.Logger) -> None:
    """What replaying the journal (map_journal.JournalReplay) did, when it did anything."""
    if journal.frames:
        logger.info("map state %s: %d frames replayed from the journal", path, journal.frames)
    if journal.cut:
        logger.warning("map state %s: the journal ends at frame %d (%s); a frame after it was not written",
                       path, journal.next, journal.cut)
    if journal.removed:
        logger.warning("map state %s: %d journal segments after frames that were not written were removed",
                       path, journal.removed)
