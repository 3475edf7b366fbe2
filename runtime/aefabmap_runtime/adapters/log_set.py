"""The files of one log set: how they are named, which ones are ours, in what order they are read.

A node's ``--mcap`` target names a *log set* (a run may write several files, see
runtime/aefabmap_runtime/adapters/rotating_log.py, and a restarted service writes new ones beside the old):

================================ ==============================================================
target                           files, in order
================================ ==============================================================
``DIR/`` (or an existing dir)    ``DIR/lcd-YYYYmmdd-HHMMSS-0001.mcap``, ``...-0002.mcap``, ...
                                 (UTC time the file was opened, then its number in the set;
                                 a missing ``DIR/`` is created with its parents)
``run-{n}.mcap`` (one ``{n}``)   ``run-0001.mcap``, ``run-0002.mcap``, ...
``run.mcap`` (plain path)        ``run.mcap`` (the first file, as before rotation existed),
                                 then ``run-0001.mcap``, ``run-0002.mcap``, ...
================================ ==============================================================

A new file takes the number after the highest one present (so name order is creation order,
also after the oldest were deleted) and is created exclusively: an existing file is never
overwritten, a restart with the same target continues the numbering. Numbers have at least
four digits (more past 9999). A file is *ours* when its name matches the set's pattern
strictly, it is a regular file (not a symlink, never followed) and it starts with the MCAP
magic; only ours are counted in a budget or deleted.

Reading (replay): :func:`log_files` expands directories, globs and lists into MCAP files in
run order, and :class:`LogSetReader` reads them one after the other as one run.
"""

from __future__ import annotations

import glob
import os
import re
import stat
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

from aefabmap_runtime.errors import ConfigError, LogError
from aefabmap_runtime.adapters.mcap_log import (
    LoggedImage,
    RUN_CONFIG_METADATA,
    McapLogReader,
    ReadStatus,
    read_log_metadata,
)
from aefabmap_runtime.core.records.messages import FrameResult, StatsMessage

T = TypeVar("T")

MCAP_MAGIC = b"\x89MCAP0\r\n"
#: Metadata record of each file of a set: {"run_started_ns", "index" (1-based, in the run),
#: "opened_ns", "previous" (name of the run's previous file, or null)}.
LOG_FILE_METADATA = "aefabmap.log_file"
#: Prefix of the files of a directory target.
DIR_PREFIX = "lcd-"
_PLACEHOLDER = "{n}"
_NUMBER = r"(\d{4,})"


@dataclass(frozen=True)
class LogFile:
    """One file of a set: its path, number in the set (0: the plain target itself) and size."""

    path: Path
    number: int
    size: int


class LogSet:
    """The naming scheme of a ``--mcap`` target (see the module docstring).

    Raises ConfigError for a malformed pattern (several ``{n}``, ``{n}`` in the directory part).
    """

    def __init__(self, target: str | os.PathLike) -> None:
        text = os.fspath(target)
        if not text:
            raise ConfigError("the MCAP log target is empty")
        self.target = text
        is_dir = text.endswith(("/", os.sep)) or Path(text).is_dir()
        if is_dir:
            self.directory = Path(text)
            self.kind = "dir"
            self._regex = re.compile(re.escape(DIR_PREFIX) + r"\d{8}-\d{6}-" + _NUMBER + r"\.mcap")
            return
        path = Path(text)
        self.directory = path.parent
        name = path.name
        if _PLACEHOLDER in str(path.parent):
            raise ConfigError(f"MCAP log pattern {text!r}: {_PLACEHOLDER} may only appear in the file name")
        count = name.count(_PLACEHOLDER)
        if count > 1:
            raise ConfigError(f"MCAP log pattern {text!r} has {count} {_PLACEHOLDER}; one is allowed")
        if count == 1:
            self.kind = "pattern"
            self._prefix, self._suffix = name.split(_PLACEHOLDER)
            self._regex = re.compile(re.escape(self._prefix) + _NUMBER + re.escape(self._suffix))
        else:
            self.kind = "plain"
            self._base = name
            self._stem, self._ext = os.path.splitext(name)
            self._regex = re.compile(re.escape(self._stem) + r"(?:-" + _NUMBER + r")?" + re.escape(self._ext))

    # ------------------------------------------------------------------ naming
    def number_of(self, name: str) -> int | None:
        """The number of file name ``name`` in this set (0: the plain target), None if not of the set."""
        m = self._regex.fullmatch(name)
        if m is None:
            return None
        return int(m.group(1)) if m.group(1) is not None else 0

    def name_for(self, number: int, opened_ns: int | None = None) -> str:
        """File name of number ``number`` (opened at ``opened_ns``, ns since the epoch, for a directory)."""
        if self.kind == "dir":
            stamp = time.strftime("%Y%m%d-%H%M%S", time.gmtime((time.time_ns() if opened_ns is None else opened_ns) / 1e9))
            return f"{DIR_PREFIX}{stamp}-{number:04d}.mcap"
        if self.kind == "pattern":
            return f"{self._prefix}{number:04d}{self._suffix}"
        return self._base if number == 0 else f"{self._stem}-{number:04d}{self._ext}"

    def first_number(self) -> int:
        """Number of the next new file: one past the highest name of the set present (any kind of
        entry, so a symlink or directory of that name is never replaced either)."""
        highest = -1 if self.kind == "plain" else 0
        for name in self._names():
            n = self.number_of(name)
            if n is not None:
                highest = max(highest, n)
        return highest + 1

    def create_next(self, open_file: Callable[[Path, int], T]) -> tuple[Path, T]:
        """Create the next new file of the set, never replacing an existing entry.

        open_file(path, opened_ns) must create `path` exclusively (LogError caused by
        FileExistsError when the name is taken, e.g. by another writer between listing and
        creating: the next number is tried). Returns (path, what open_file returned).
        """
        number = self.first_number()
        for _ in range(100):
            opened_ns = time.time_ns()
            path = self.directory / self.name_for(number, opened_ns)
            try:
                return path, open_file(path, opened_ns)
            except LogError as exc:
                if not isinstance(exc.__cause__, FileExistsError):
                    raise
                number += 1
        raise LogError(f"cannot create MCAP log in {self.directory}: no free name after 100 tries")

    def _names(self) -> list[str]:
        try:
            return os.listdir(self.directory)
        except FileNotFoundError:
            return []
        except OSError as exc:
            raise LogError(f"cannot list the MCAP log directory {self.directory}: {exc.strerror or exc}") from exc

    # ------------------------------------------------------------------ our files
    def files(self) -> list[LogFile]:
        """Our files of this set (see the module docstring), oldest first (by number)."""
        out = []
        for name in self._names():
            number = self.number_of(name)
            if number is None:
                continue
            path = self.directory / name
            size = _our_mcap_size(path)
            if size is not None:
                out.append(LogFile(path, number, size))
        return sorted(out, key=lambda f: (f.number, f.path.name))

    def make_directory(self) -> None:
        """Create a directory target's directory, with its parents, when it does not exist (the
        README's ``--mcap logs/`` on a fresh machine); LogError when it cannot be. The directory of
        a file or pattern target is not created: a typo there is refused by check_writable."""
        if self.kind != "dir" or self.directory.is_dir():
            return
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise LogError(f"cannot create the MCAP log directory {self.directory}: {exc.strerror or exc}") from exc

    def check_writable(self) -> None:
        """LogError when the set's directory is missing or not writable (checked before a run
        starts, so a bad target is refused before any file or network activity)."""
        d = self.directory
        if not d.is_dir():
            raise LogError(f"cannot create MCAP log {self.target}: directory {d} does not exist")
        if not os.access(d, os.W_OK | os.X_OK):
            raise LogError(f"cannot create MCAP log {self.target}: directory {d} is not writable")

    def trim_to_budget(self, budget_bytes: int, reserve_bytes: int, keep: Path | None) -> list[LogFile]:
        """Delete the oldest of our closed files until their total plus ``reserve_bytes`` (room kept
        for the open file) is within ``budget_bytes``. ``keep`` (the open file) is never deleted.
        Returns the files deleted; a file that cannot be deleted is skipped."""
        closed = [f for f in self.files() if keep is None or f.path != keep]
        total = sum(f.size for f in closed) + reserve_bytes
        deleted = []
        for f in closed:
            if total <= budget_bytes:
                break
            try:
                os.unlink(f.path)
            except FileNotFoundError:
                pass
            except OSError:
                continue
            total -= f.size
            deleted.append(f)
        return deleted


def _our_mcap_size(path: Path) -> int | None:
    """Size of ``path`` if it is a regular file (not followed if a symlink) starting with the
    MCAP magic, else None."""
    try:
        st = os.lstat(path)
        if not stat.S_ISREG(st.st_mode):
            return None
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0))
        try:
            magic = os.read(fd, len(MCAP_MAGIC))
        finally:
            os.close(fd)
    except OSError:
        return None
    return st.st_size if magic == MCAP_MAGIC else None


def free_bytes(directory: str | os.PathLike) -> int:
    """Bytes available to this user on the filesystem holding ``directory`` (os.statvfs)."""
    st = os.statvfs(directory)
    return st.f_bavail * st.f_frsize


# ============================================================================ reading a set


def _has_glob(text: str) -> bool:
    return any(c in text for c in "*?[")


def _order_key(path: Path) -> tuple:
    """Run order: the run's start, the file's index in it, then the name."""
    try:
        meta = read_log_metadata(path).get(LOG_FILE_METADATA) or {}
    except LogError:
        meta = {}
    started = meta.get("run_started_ns")
    index = meta.get("index")
    ok_started = isinstance(started, int) and not isinstance(started, bool)
    ok_index = isinstance(index, int) and not isinstance(index, bool)
    # Files without set metadata (older logs, bags) sort by name after nothing in particular:
    # key (0, name) keeps their given relative order by name.
    if not ok_started:
        return (0, 0, 0, path.name)
    return (1, started, index if ok_index else 0, path.name)


def log_files(sources: str | os.PathLike | Sequence[str | os.PathLike]) -> list[Path]:
    """The MCAP files named by ``sources`` in run order.

    Each source is a file, a directory (its ``*.mcap`` regular files) or a glob pattern.
    Files carrying set metadata (LOG_FILE_METADATA) are ordered by run start then index in
    the run; others by name. Raises LogError when a source names nothing.
    """
    items = [sources] if isinstance(sources, (str, os.PathLike)) else list(sources)
    found: dict[Path, None] = {}
    for item in items:
        text = os.fspath(item)
        path = Path(text)
        if path.is_dir():
            names = sorted(p for p in path.iterdir() if p.suffix == ".mcap" and p.is_file() and not p.is_symlink())
            if not names:
                raise LogError(f"no .mcap files in directory {path}")
        elif not path.exists() and _has_glob(text):
            names = sorted(Path(p) for p in glob.glob(text) if Path(p).is_file())
            if not names:
                raise LogError(f"no files match {text!r}")
        else:
            if not path.is_file():
                raise LogError(f"MCAP log {path} " + ("is not a regular file" if path.exists() else "does not exist"))
            names = [path]
        for p in names:
            found.setdefault(p, None)
    if len(found) == 1:
        return list(found)
    return sorted(found, key=_order_key)


class LogSetReader:
    """McapLogReader's interface over several files read in order as one run.

    ``results``/``stats`` are concatenated; ``metadata`` (manifest, run config, format) is
    the first file's; ``status`` adds the counters up (``truncated`` if any file was,
    ``files`` lists them) and ``runs`` counts the distinct runs met (run_started_ns). Each image
    carries the index of its run (``LoggedImage.run``); ``map_starts[i]`` is the frame run i's map
    started at (the ``map_start`` its run configuration records: 0 for an empty map, N for a map
    state loaded at frame N; None for logs written before it was recorded; known once frames()
    reached the run, ``file_map_starts`` per file from the start) and ``results_by_run[i]`` its
    logged results.
    """

    def __init__(self, paths: Sequence[Path], *, image_topic: str | None = None) -> None:
        if not paths:
            raise LogError("no MCAP files to read")
        self.paths = list(paths)
        self._readers = [McapLogReader(p, image_topic=image_topic) for p in self.paths]
        self.results: list[FrameResult] = []
        self.stats: list[StatsMessage] = []
        self.status = ReadStatus(f"{self.paths[0].parent} ({len(self.paths)} files)",
                                 files=[str(p) for p in self.paths])
        self.runs = 0
        metas = [read_log_metadata(p) for p in self.paths]  # records written at open: cheap
        self.file_map_starts = [_map_start(m) for m in metas]
        self._file_runs = [(m.get(LOG_FILE_METADATA) or {}).get("run_started_ns", str(p))
                           for m, p in zip(metas, self.paths, strict=True)]
        self.map_starts: list[int | None] = []  # per run, filled as frames() reaches each run
        self.results_by_run: list[list[FrameResult]] = []
        self._spent = False

    @property
    def metadata(self) -> dict[str, dict]:
        return self._readers[0].metadata

    @property
    def manifest(self) -> dict | None:
        return self._readers[0].manifest

    @property
    def run_config(self) -> dict | None:
        return self._readers[0].run_config

    @property
    def format_version(self) -> tuple[int, int] | None:
        """The oldest format among the files read (fields newer than it are not comparable)."""
        versions = [v for r in self._readers if (v := r.format_version) is not None]
        return min(versions) if versions else None

    @property
    def extraction_version(self) -> int | None:
        """The files' extraction version when they all record the same one, else None."""
        versions = {r.extraction_version for r in self._readers}
        return versions.pop() if len(versions) == 1 else None

    def frames(self) -> Iterator[LoggedImage]:
        if self._spent:
            raise LogError(f"{self.status.path}: a log reader can be iterated only once")
        self._spent = True
        runs: list = []
        for reader, start, run in zip(self._readers, self.file_map_starts, self._file_runs, strict=True):
            if not runs or runs[-1] != run:  # the files of one run are consecutive in reading order
                runs.append(run)
                self.map_starts.append(start)
                self.results_by_run.append([])
            index = len(runs) - 1
            for image in reader.frames():
                image.run = index
                yield image
            self.results.extend(reader.results)
            self.results_by_run[index].extend(reader.results)
            self.stats.extend(reader.stats)
            self._add_status(reader.status)
        self.runs = len(runs)

    def _add_status(self, s: ReadStatus) -> None:
        t = self.status
        t.messages_read += s.messages_read
        t.images_read += s.images_read
        t.undecodable_messages += s.undecodable_messages
        t.invalid_messages += s.invalid_messages
        t.last_invalid = s.last_invalid or t.last_invalid
        t.image_topic = t.image_topic or s.image_topic
        t.format_version = t.format_version or s.format_version
        t.ignored_image_topics += [x for x in s.ignored_image_topics if x not in t.ignored_image_topics]
        for topic, n in s.unknown_topics.items():
            t.unknown_topics[topic] = t.unknown_topics.get(topic, 0) + n
        if s.truncated:
            t.truncated = True
            t.reason = f"{Path(s.path).name}: {s.reason}"


def _map_start(metadata: dict[str, dict]) -> int | None:
    """The frame the run that wrote a file (its metadata records) started its map at (None: not recorded)."""
    start = (metadata.get(RUN_CONFIG_METADATA) or {}).get("map_start")
    frame = start.get("frame") if isinstance(start, dict) else None
    return frame if isinstance(frame, int) and not isinstance(frame, bool) and frame >= 0 else None


def open_log_reader(sources, *, image_topic: str | None = None) -> McapLogReader | LogSetReader:
    """A reader of ``sources`` (see log_files): McapLogReader for one file, else LogSetReader."""
    paths = log_files(sources)
    if len(paths) == 1:
        return McapLogReader(paths[0], image_topic=image_topic)
    return LogSetReader(paths, image_topic=image_topic)
