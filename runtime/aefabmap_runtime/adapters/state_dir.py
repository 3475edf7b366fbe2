"""The map on disk (``--state DIR``): crash-safe snapshots of the detector's state.

Layout of DIR::

    CURRENT               one line: the name of the snapshot to load ("snap-000012")
    snap-000012/          the current snapshot: manifest.json + one .npy per array
    snap-000011/          the previous one (kept until the next snapshot is complete)
    lock                  flock'ed by the process that owns DIR

A snapshot directory is written under a temporary name, every file fsync'ed, the directory
fsync'ed, renamed to ``snap-NNNNNN`` and DIR fsync'ed; only then is CURRENT replaced
(temporary file, fsync, atomic rename, fsync DIR). A crash or a failed write at any point
leaves CURRENT naming the previous complete snapshot. manifest.json holds the format
version, the bundle id (sha256 of the bundle manifest), counts, the state's scalars and the
sha256 of every array file; arrays are plain .npy (no pickles), read with the checked loader
(runtime/aefabmap_runtime/adapters/npy_file.py) and then checked again by the core (runtime/aefabmap_runtime/core/records/map_state.py).

Between snapshots the live node appends each frame to a journal in DIR (``journal-*`` files,
runtime/aefabmap_runtime/adapters/map_journal.py); loading replays it after the snapshot, and a durable
snapshot removes the journal segments it makes obsolete.
"""

from __future__ import annotations

import errno
import fcntl
import hashlib
import io
import json
import os
import re
import shutil
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Self

import numpy as np

from aefabmap_runtime.errors import AefabmapError, StateError
from aefabmap_runtime.adapters.durable_files import fsync_dir, open_regular
from aefabmap_runtime.adapters.map_journal import remove_segments_before, replay_journal
from aefabmap_runtime.adapters.npy_file import load_npy
from aefabmap_runtime.core.records.map_state import MapState

FORMAT = "aefabmap-map-state"
FORMAT_VERSION = 1
CURRENT_NAME = "CURRENT"
MANIFEST_NAME = "manifest.json"
LOCK_NAME = "lock"
_SNAP_RE = re.compile(r"^snap-(\d{6,12})$")
_ARRAY_RE = re.compile(r"^[a-z0-9_.]{1,120}$")
_MAX_MANIFEST_BYTES = 1 << 20


def bundle_id(manifest: dict) -> str:
    """sha256 of the bundle manifest in canonical JSON (it lists every bundle file's sha256)."""
    text = json.dumps(manifest, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()


def _write_file(path: Path, data: bytes) -> None:
    with open(path, "xb") as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())


def _npy_bytes(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(a), allow_pickle=False)
    return buf.getvalue()


@dataclass
class SnapshotInfo:
    """One written snapshot: its directory, bytes on disk, places and write time (s)."""

    path: Path
    nbytes: int
    n_places: int
    seconds: float


class MapStateDir:
    """A state directory owned (flock) by this process; ``open`` it before use, ``close`` after.

    bundle: the id (bundle_id) that states in it must carry. read_only: the directory is only
    read (localization): it must exist; it is shared with other readers (a shared lock on its
    lock file when there is one) and nothing in it is created, changed or removed.
    """

    def __init__(self, path: str | Path, bundle: str, read_only: bool = False) -> None:
        self.path = Path(path)
        self.bundle = bundle
        self.read_only = read_only
        self._lock_fd: int | None = None

    def open(self) -> Self:
        if self.read_only:
            return self._open_shared()
        try:
            self.path.mkdir(parents=True, exist_ok=True)
            if not self.path.is_dir():  # DIR itself may be a link (e.g. to a data partition); its files may not
                raise StateError(f"state directory {self.path} is not a directory")
            fd = os.open(self.path / LOCK_NAME, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o644)
        except OSError as exc:
            raise StateError(f"cannot open state directory {self.path}: {exc.strerror or exc}") from None
        return self._lock(fd, fcntl.LOCK_EX, "another process")

    def _open_shared(self) -> Self:
        """Open for reading only: the directory must exist; a writer holding it is refused."""
        if not self.path.is_dir():
            raise StateError(f"state directory {self.path} does not exist or is not a directory")
        lock = self.path / LOCK_NAME
        if not lock.exists():
            return self  # a directory no run has written a lock into: nothing to share it with
        try:
            fd = open_regular(lock)
        except OSError as exc:
            raise StateError(f"cannot open state directory {self.path}: {exc.strerror or exc}") from None
        return self._lock(fd, fcntl.LOCK_SH, "a process that writes it")

    def _lock(self, fd: int, mode: int, holder: str) -> Self:
        """Hold the lock file `fd` with flock `mode` (never waiting); StateError naming `holder`
        when another process holds it in a mode that excludes this one."""
        try:
            fcntl.flock(fd, mode | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            raise StateError(f"state directory {self.path} is in use by {holder}") from None
        self._lock_fd = fd
        return self

    def close(self) -> None:
        if self._lock_fd is not None:
            os.close(self._lock_fd)
            self._lock_fd = None

    def __enter__(self) -> Self:
        return self.open()

    def __exit__(self, *exc_info) -> None:
        self.close()

    # -- reading ---------------------------------------------------------------------------

    def current(self) -> str | None:
        """Name of the current snapshot (None: the directory holds no state yet)."""
        p = self.path / CURRENT_NAME
        if not p.exists() and not p.is_symlink():
            return None
        try:
            fd = open_regular(p)
            with os.fdopen(fd, "rb") as fh:
                text = fh.read(64).decode("ascii", "replace").strip()
        except OSError as exc:
            raise StateError(f"{p}: cannot read: {exc.strerror or exc}") from None
        if not _SNAP_RE.match(text):
            raise StateError(f"{p} does not name a snapshot (got {text[:30]!r})")
        return text

    def load(self) -> MapState | None:
        """The current snapshot's state, checked (format, bundle, checksums, headers); None if none."""
        name = self.current()
        if name is None:
            return None
        snap = self.path / name
        try:
            if snap.is_symlink() or not snap.is_dir():
                raise StateError(f"state snapshot {snap} is missing or not a directory")
            manifest = self._read_manifest(snap)
            arrays = {key: self._read_array(snap, key, entry) for key, entry in manifest["arrays"].items()}
        except StateError as exc:
            older = sorted(p.name for p in self.path.iterdir() if _SNAP_RE.match(p.name) and p.name < name)
            if older:  # refused all the same: which map to fall back to is the operator's decision
                raise StateError(f"{exc}; the previous snapshot {older[-1]} is in {self.path} "
                                 f"(write its name into {CURRENT_NAME} to use it)") from None
            raise
        return MapState(arrays, manifest["scalars"])

    def _read_manifest(self, snap: Path) -> dict:
        p = snap / MANIFEST_NAME
        try:
            fd = open_regular(p)
            with os.fdopen(fd, "rb") as fh:
                raw = fh.read(_MAX_MANIFEST_BYTES + 1)
            if len(raw) > _MAX_MANIFEST_BYTES:
                raise StateError(f"{p} is larger than {_MAX_MANIFEST_BYTES} bytes")
            doc = json.loads(raw)
        except OSError as exc:
            raise StateError(f"{p}: cannot read: {exc.strerror or exc}") from None
        except (ValueError, UnicodeDecodeError) as exc:
            raise StateError(f"{p}: not valid JSON ({exc})") from None
        if not isinstance(doc, dict) or doc.get("format") != FORMAT:
            raise StateError(f"{p} is not an aefabmap map state")
        version = doc.get("version")
        if not isinstance(version, int) or isinstance(version, bool):
            raise StateError(f"{p}: format version {str(version)[:20]!r} is not an integer")
        if version > FORMAT_VERSION:
            raise StateError(f"{p}: map state format version {version} is newer than this aefabmap reads ({FORMAT_VERSION})")
        if version < 1:
            raise StateError(f"{p}: unknown map state format version {version}")
        if doc.get("bundle") != self.bundle:
            raise StateError(f"{snap}: map state was built with another model bundle (bundle id {str(doc.get('bundle'))[:16]}...)")
        arrays, scalars = doc.get("arrays"), doc.get("scalars")
        if not isinstance(arrays, dict) or not isinstance(scalars, dict):
            raise StateError(f"{p}: 'arrays' and 'scalars' must be objects")
        for key, entry in arrays.items():
            if not isinstance(key, str) or not _ARRAY_RE.match(key) or not isinstance(entry, dict):
                raise StateError(f"{p}: bad array entry {str(key)[:40]!r}")
            if not isinstance(entry.get("sha256"), str):
                raise StateError(f"{p}: array {key!r} has no sha256")
        for key, value in scalars.items():
            if not isinstance(value, (int, float, str, bool, type(None))):
                raise StateError(f"{p}: scalar {str(key)[:40]!r} is not a number, string, bool or null")
        return doc

    def _read_array(self, snap: Path, key: str, entry: dict) -> np.ndarray:
        p = snap / f"{key}.npy"
        label = f"{snap.name}/{key}.npy"
        try:
            fd = open_regular(p)  # a symlink leaving DIR is refused here
        except OSError as exc:
            raise StateError(f"{label}: cannot open: {exc.strerror or exc}") from None
        with os.fdopen(fd, "rb") as fh:
            h = hashlib.sha256()
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
            if h.hexdigest() != entry["sha256"]:
                raise StateError(f"{label}: checksum mismatch (file corrupt, truncated or modified)")
            fh.seek(0)
            return load_npy(fh, label, kinds="biuf", error=StateError)

    # -- writing ---------------------------------------------------------------------------

    def save(self, state: MapState) -> SnapshotInfo:
        """Write ``state`` as the new current snapshot (see the module doc); on any failure the
        previous snapshot stays current and StateError is raised. When the disk is full, the
        snapshots older than the current one are removed and the write is tried once more: the
        newest complete map matters more than the one before it."""
        try:
            return self._save(state)
        except _DiskFull:
            current = self.current_or_none()
            self._prune(keep=(current,))
            try:
                return self._save(state)
            except _DiskFull as exc:
                kept = self._places_in(current)
                raise StateError(f"cannot write map state to {self.path}: {exc.strerror}; the current snapshot "
                                 f"({kept} places) stays, {state.scalars.get('n_alive')} places in the map now "
                                 "were not saved") from None

    def _places_in(self, name: str | None) -> int | None:
        try:
            return None if name is None else self._read_manifest(self.path / name).get("n_places")
        except StateError:
            return None

    def _save(self, state: MapState) -> SnapshotInfo:
        t0 = time.perf_counter()
        state.resolve()  # deferred parts (keypoints) are packed here, by the writing thread
        current = self.current_or_none()
        # Past every snapshot present: one orphaned by a crash before CURRENT moved is not reused.
        taken = [int(m.group(1)) for p in self.path.iterdir() if (m := _SNAP_RE.match(p.name))]
        number = max(taken, default=0) + 1
        name = f"snap-{number:06d}"
        tmp = self.path / f".tmp-{name}-{os.getpid()}"
        try:
            if tmp.exists():
                shutil.rmtree(tmp)
            tmp.mkdir()
            entries, total = {}, 0
            for key, a in state.arrays.items():
                if not _ARRAY_RE.match(key):
                    raise StateError(f"map state array name {key!r} is not a plain file name")
                data = _npy_bytes(a)
                _write_file(tmp / f"{key}.npy", data)
                entries[key] = {"sha256": hashlib.sha256(data).hexdigest(), "dtype": str(a.dtype), "shape": list(a.shape)}
                total += len(data)
            doc = {"format": FORMAT, "version": FORMAT_VERSION, "bundle": self.bundle,
                   "written_ns": time.time_ns(), "n_places": state.scalars.get("n_alive"),
                   "scalars": state.scalars, "arrays": entries}
            data = json.dumps(doc, indent=1).encode()
            _write_file(tmp / MANIFEST_NAME, data)
            total += len(data)
            fsync_dir(tmp)
            os.replace(tmp, self.path / name)
            fsync_dir(self.path)
            cur_tmp = self.path / f".{CURRENT_NAME}.tmp"
            cur_tmp.unlink(missing_ok=True)
            _write_file(cur_tmp, (name + "\n").encode())
            os.replace(cur_tmp, self.path / CURRENT_NAME)
            fsync_dir(self.path)
        except OSError as exc:
            shutil.rmtree(tmp, ignore_errors=True)
            (self.path / f".{CURRENT_NAME}.tmp").unlink(missing_ok=True)
            if exc.errno in (errno.ENOSPC, errno.EDQUOT):
                raise _DiskFull(exc.errno, exc.strerror) from None
            raise StateError(f"cannot write map state to {self.path}: {exc.strerror or exc}") from None
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        self._prune(keep=(name, current))

        remove_segments_before(self.path, int(state.scalars.get("sequence") or 0))
        return SnapshotInfo(self.path / name, total, int(state.scalars.get("n_alive") or 0), time.perf_counter() - t0)

    def current_or_none(self) -> str | None:
        """Like current(), but an unreadable CURRENT counts as none (a save may replace it)."""
        try:
            return self.current()
        except StateError:
            return None

    def _prune(self, keep: tuple) -> None:
        """Remove snapshots other than the current and previous one, and stale temporaries."""
        for p in self.path.iterdir():
            if p.name in keep or not (_SNAP_RE.match(p.name) or p.name.startswith(".tmp-snap-")):
                continue
            if p.is_symlink():
                p.unlink(missing_ok=True)
            else:
                shutil.rmtree(p, ignore_errors=True)


class _DiskFull(OSError):
    """A snapshot write ran out of space (internal: save() retries once after pruning)."""


def load_map(detector, directory: MapStateDir):
    """Load the directory's current state, then replay its journal, into ``detector``; returns
    (the snapshot's MapState or None, the map_journal.JournalReplay). A read-only directory is
    only read (segments the journal cannot reach stay where they are)."""

    state = directory.load()
    if state is not None:
        detector.load_state(state)
    return state, replay_journal(detector, directory, remove_unreachable=not directory.read_only)


def load_into(detector, directory: MapStateDir) -> bool:
    """`load_map`: True when it loaded anything, False when the directory holds no map."""
    state, journal = load_map(detector, directory)
    return state is not None or journal.frames > 0


@dataclass(frozen=True)
class SnapshotPolicy:
    """When to snapshot: every ``seconds`` of run time or every ``places`` new places."""

    seconds: float | None = 60.0
    places: int | None = None

    @classmethod
    def parse(cls, text: str) -> SnapshotPolicy:
        """"30s", "5m" (time) or "100p" (places added)."""
        from aefabmap_runtime.errors import ConfigError

        m = re.fullmatch(r"\s*(\d+(?:\.\d+)?)\s*([smp])\s*", str(text))
        if not m or float(m.group(1)) <= 0:
            raise ConfigError(f"--snapshot-every takes e.g. 60s, 5m or 100p (places), got {str(text)[:40]!r}")
        value, unit = float(m.group(1)), m.group(2)
        if unit == "p":
            if value != int(value):
                raise ConfigError(f"--snapshot-every places must be a whole number, got {text!r}")
            return cls(seconds=None, places=int(value))
        return cls(seconds=value * (60.0 if unit == "m" else 1.0), places=None)


class Snapshotter:
    """The node's collaborator: snapshots the detector between frames when the policy says so,
    and once more at the end of the run (``final``). A failed periodic snapshot is reported
    (``on_error``) and counted, the run goes on and the previous snapshot stays current.

    background: take the state between frames (index arrays copied, keypoints referenced) but
    pack the keypoints and write it all in a thread, so that frames are not held up by the disk; at most
    one write is in flight (a due snapshot waits for the next frame after it) and ``final``
    waits for it before writing the last one.

    journal: a map_journal.MapJournal recording every frame between snapshots. With one, a
    snapshot that cannot be written (the final one included) is reported, never raised: the
    journal keeps the frames it could write, and while some are not on disk a snapshot is tried
    again every ``retry_s`` seconds (it writes them all once the disk has room again).
    """

    def __init__(self, detector, directory: MapStateDir, policy: SnapshotPolicy, *,
                 on_error=None, on_saved=None, clock=time.monotonic, background: bool = False,
                 journal=None, retry_s: float = 10.0) -> None:
        self.detector, self.directory, self.policy = detector, directory, policy
        self.on_error, self.on_saved, self.clock = on_error, on_saved, clock
        self.background = background
        self.journal, self.retry_s = journal, retry_s
        self.failures = 0
        self.saved: list[SnapshotInfo] = []
        self._writer: threading.Thread | None = None
        self._mark()

    def _mark(self) -> None:
        self._t = self.clock()
        self._inserted = self._places_made()

    def _places_made(self) -> int:
        return int(self.detector.frames_inserted)

    def record_frame(self) -> None:
        """Append the frame the detector just took to the journal (as durable as the journal
        makes it), so that its result may go out; `after_frame` does it too when not done."""
        if self.journal is not None:
            self.journal.after_frame()

    def after_frame(self) -> None:
        self.record_frame()
        p = self.policy
        due = (p.seconds is not None and self.clock() - self._t >= p.seconds) or (
            p.places is not None and self._places_made() - self._inserted >= p.places) or self._catch_up_due()
        if not due or (self._writer is not None and self._writer.is_alive()):
            return
        state = self.detector.state()
        if self.journal is not None:
            self.journal.rotate()  # the frames from here on continue this snapshot
        self._mark()
        if self.background:
            self._writer = threading.Thread(target=self._write, args=(state, False), name="map-snapshot", daemon=True)
            self._writer.start()
        else:
            self._write(state, final=False)

    def _catch_up_due(self) -> bool:
        """Frames the journal could not write are waiting for a snapshot, the last tried retry_s ago."""
        return self.journal is not None and self.clock() - self._t >= self.retry_s and self.journal.behind

    def final(self) -> SnapshotInfo | None:
        """The stop path's snapshot (after any write in flight). When it cannot be written:
        StateError without a journal; with one, reported (on_error) and None."""
        self.join()
        if self.journal is not None:
            self.journal.after_frame()
        return self._write(self.detector.state(), final=True)

    def join(self) -> None:
        if self._writer is not None:
            self._writer.join()
            self._writer = None

    def _write(self, state: MapState, final: bool) -> SnapshotInfo | None:
        try:
            info = self.directory.save(state)
        except AefabmapError as exc:
            self.failures += 1
            if final and self.journal is None:
                raise
            if self.on_error is not None:
                self.on_error(exc)
            return None
        if self.journal is not None:
            self.journal.snapshot_durable(int(state.scalars["sequence"]), info.n_places)
        self.saved.append(info)
        if self.on_saved is not None:
            self.on_saved(info)
        return info
