"""The map a run keeps on disk (--state DIR): the state directory opened and its map loaded, and
for the live node the journal of the frames between snapshots and the snapshotter, closed in order
(runtime/aefabmap_runtime/adapters/state_dir.py, runtime/aefabmap_runtime/adapters/map_journal.py)."""

from __future__ import annotations

import logging
from pathlib import Path

from aefabmap_runtime.adapters.map_journal import MapJournal, StateReport
from aefabmap_runtime.adapters.state_dir import MapStateDir, SnapshotPolicy, Snapshotter, bundle_id, load_map
from aefabmap_runtime.core.run_config import recorded_settings_differences
from aefabmap_runtime.errors import ConfigError, StateError


def open_state(path: str | Path, detector, logger: logging.Logger, read_only: bool = False) -> MapStateDir:
    """Open (lock) the state directory DIR for ``detector``'s bundle and load its map if present:
    the current snapshot, then the frames of its journal. A snapshot built with other detector
    settings loads (it continues with this run's), with a warning naming them; a journal must
    match them (runtime/aefabmap_runtime/adapters/map_journal.py). read_only: DIR is only read
    (MapStateDir read_only)."""
    directory = MapStateDir(path, bundle_id(detector.manifest), read_only=read_only).open()
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


def open_frozen_map(path: str | Path, detector, logger: logging.Logger) -> MapStateDir:
    """Localization (--localize): load the map of the state directory DIR read-only into
    ``detector`` and make its map read-only (core/map/place_map.py): frames are ranked and verified
    against it, none is inserted (only the frames the building run still held back enter, on its
    schedule), nothing is evicted or written back, and DIR is never written. Returns the open
    directory (close it after the run). StateError when DIR holds no map."""
    directory = open_state(path, detector, logger, read_only=True)
    if detector.n_places == 0:
        directory.close()
        raise StateError(f"--localize needs a map: state directory {path} holds no places (build one with "
                         "`run --state DIR` first)")
    detector.map.read_only = True
    logger.info("localizing against the map in %s: %d places and %d held back for the insertion delay, "
                "read-only (no frame of this run is inserted, nothing is written)",
                path, detector.n_places, len(detector.map.queued()))
    return directory


def new_map_saver(path: str | Path, logger: logging.Logger):
    """detector -> None: saves its map to the state directory ``path``, which must hold no map
    (checked now, before the run: `eval --state` builds a new one)."""
    probe = MapStateDir(path, "")
    if probe.current_or_none() is not None or (probe.path / "CURRENT").exists():
        raise ConfigError(f"state directory {path} already holds a map; eval builds a new one")

    def save(detector) -> None:
        with MapStateDir(path, bundle_id(detector.manifest)) as directory:
            info = directory.save(detector.state())
        logger.info("map state saved to %s: %d places, %d bytes", info.path, info.n_places, info.nbytes)

    return save


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


class NodeState:
    """The live node's map on disk: the state directory (`open_state`), the journal every frame
    between snapshots goes to (a failing disk loses only what it could not take) and the
    snapshotter that writes in the background by `policy`. `finish` on the normal stop path;
    `close` always (waits for a snapshot being written, then closes the journal and the directory)."""

    def __init__(self, path: str | Path, detector, policy: SnapshotPolicy, logger: logging.Logger) -> None:
        self.logger = logger
        self.directory = open_state(path, detector, logger)
        self.journal: MapJournal | None = None
        self.snapshotter: Snapshotter | None = None
        try:
            self.journal = MapJournal(self.directory, detector, on_error=lambda exc: logger.warning("%s", exc))
            self.snapshotter = Snapshotter(
                detector, self.directory, policy,
                on_error=lambda exc: logger.warning("snapshot failed, the previous one is kept: %s", exc),
                on_saved=lambda info: logger.debug("snapshot %s: %d places, %d bytes, %.3f s",
                                                   info.path.name, info.n_places, info.nbytes, info.seconds),
                background=True, journal=self.journal,
            )
        except BaseException:
            self.close()
            raise

    def finish(self) -> StateReport:
        """After the run: log the last snapshot and what the directory keeps; the journal is closed."""
        if self.snapshotter.saved:
            last = self.snapshotter.saved[-1]
            self.logger.info("map state saved to %s: %d places, %d bytes", last.path, last.n_places, last.nbytes)
        self.journal.close()
        report = self.journal.report()
        (self.logger.warning if report.frames_not_written else self.logger.info)("%s", report.line())
        return report

    def close(self) -> None:
        if self.snapshotter is not None:
            self.snapshotter.join()  # a snapshot being written when the run failed
        if self.journal is not None:
            self.journal.close()
        self.directory.close()
