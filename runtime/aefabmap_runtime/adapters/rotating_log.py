"""The node's MCAP log: rotated files, a disk budget, low-space degradation, errors counted.

:class:`RotatingLog` has McapLogWriter's writing interface (write_image / write_result /
write_stats / close) over a log set (runtime/aefabmap_runtime/adapters/log_set.py), and never raises for an
I/O problem once the run has started: detection never stops because of the log.

- Never overwrites: each file is created exclusively with the next number of the set.
- ``max_mb``: the file in progress is finished (summary, footer) and a new one started
  before it would pass max_mb; every file is a complete log on its own (schemas, channels,
  ``aefabmap.log``, manifest, run config and ``aefabmap.log_file`` metadata).
- ``budget_mb``: before a file is opened, the oldest *closed* files of the set (ours only, see
  log_set) are deleted until they plus the room for the open file (max_mb, or its current
  size when files are not rotated) fit the budget. So the set never exceeds the budget when
  max_mb is set (budget plus one file otherwise).
- Free space on the log's filesystem (os.statvfs, checked at most every
  ``space_check_interval_s``): below ``images_min_free_mb`` images are no longer logged
  (state ``images_stopped``), below ``results_min_free_mb`` nothing is (``stopped``);
  logging resumes when space comes back.
- A write error (disk full, EIO, ...) is counted (``errors``), the file is abandoned
  unfinished (readable up to its last complete chunk), state ``failed``; a new file is tried
  every ``retry_interval_s``.
"""

from __future__ import annotations

import errno
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

from aefabmap_runtime.errors import ConfigError, LogError
from aefabmap_runtime.adapters.log_set import LOG_FILE_METADATA, LogSet, free_bytes
from aefabmap_runtime.adapters.mcap_log import McapLogConfig, McapLogWriter
from aefabmap_runtime.core.records.messages import LOG_STATES

__all__ = ["LOG_STATES", "MB", "LogRotationConfig", "RotatingLog"]

MB = 1024 * 1024
#: RotatingLog.files keeps the names of the last files created (a long run may create thousands).
MAX_LISTED_FILES = 100


@dataclass(frozen=True)
class LogRotationConfig:
    """Rotation, budget and free-space settings of a node's log (sizes in MiB).

    max_mb: start a new file before the current one would pass this size (None: one file).
    budget_mb: total size of the set's files (None: unbounded); must be >= max_mb.
    images_min_free_mb: stop logging images below this free space (None: max(500, 2 * max_mb)).
    results_min_free_mb: stop logging results and stats below this free space.
    space_check_interval_s: seconds between free-space checks.
    retry_interval_s: seconds between attempts to open a new file after a write error.
    summary_reserve_bytes: room kept for a file's summary section when deciding to rotate.
    """

    max_mb: float | None = None
    budget_mb: float | None = None
    images_min_free_mb: float | None = None
    results_min_free_mb: float = 100.0
    space_check_interval_s: float = 1.0
    retry_interval_s: float = 5.0
    summary_reserve_bytes: int = 64 * 1024

    def __post_init__(self) -> None:
        for name, low in (("max_mb", 0.0), ("budget_mb", 0.0), ("images_min_free_mb", None),
                          ("results_min_free_mb", None)):
            v = getattr(self, name)
            if v is None:
                continue
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0 or v == low:
                raise ConfigError(f"log {name} must be a finite number {'> 0' if low is not None else '>= 0'} "
                                  f"(MB), got {v!r}")
        if self.max_mb is not None and self.max_mb * MB < 4 * self.summary_reserve_bytes:
            raise ConfigError(f"log max_mb must be >= {4 * self.summary_reserve_bytes / MB:.2f}, got {self.max_mb}")
        if self.budget_mb is not None and self.max_mb is not None and self.budget_mb < self.max_mb:
            raise ConfigError(f"log budget ({self.budget_mb} MB) must be >= the file size limit ({self.max_mb} MB)")
        if not (self.space_check_interval_s > 0 and self.retry_interval_s > 0):
            raise ConfigError("log space check and retry intervals must be > 0 s")

    @property
    def images_threshold_bytes(self) -> int:
        if self.images_min_free_mb is not None:
            return int(self.images_min_free_mb * MB)
        return int(max(500.0, 2 * (self.max_mb or 0)) * MB)

    @property
    def results_threshold_bytes(self) -> int:
        return int(self.results_min_free_mb * MB)

    def chunk_size(self, requested: int) -> int:
        """Chunk size for files of max_mb: at most an eighth of a file, so files fill up."""
        if self.max_mb is None:
            return requested
        return max(16 * 1024, min(requested, int(self.max_mb * MB) // 8))


class RotatingLog:
    """A node's log set being written (see the module docstring).

    target: the ``--mcap`` target (file, ``{n}`` pattern or directory, see log_set).
    Construction checks the target (ConfigError, LogError), creates a missing directory target
    (LogSet.make_directory) and opens no file; :meth:`open`
    creates the first one (LogError when it cannot: a start-time failure). After that the
    write methods never raise; ``errors``, ``state``, ``files`` (the last MAX_LISTED_FILES
    created), ``files_opened`` and ``deleted_count`` say how the log fares.
    free_space / writer_factory / clock: seams for tests (defaults: os.statvfs, McapLogWriter,
    time.monotonic).
    """

    def __init__(
        self,
        target: str | os.PathLike,
        config: McapLogConfig | None = None,
        rotation: LogRotationConfig | None = None,
        *,
        manifest: dict | None = None,
        run_config: dict | None = None,
        free_space: Callable[[Path], int] = free_bytes,
        writer_factory: Callable[..., McapLogWriter] = McapLogWriter,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.rotation = rotation or LogRotationConfig()
        base = config or McapLogConfig()
        self.config = replace(base, chunk_size=self.rotation.chunk_size(base.chunk_size))
        self.set = LogSet(target)
        self.set.make_directory()
        self.set.check_writable()
        self.manifest, self.run_config = manifest, run_config
        self._free_space, self._factory, self._clock = free_space, writer_factory, clock
        self.run_started_ns = time.time_ns()
        self.files: list[Path] = []
        self.deleted: list[Path] = []  # the last MAX_LISTED_FILES deleted
        self.deleted_count = 0
        self.errors = 0
        self.last_error = ""
        self.images_written = 0
        self.images_skipped = 0
        self.messages_skipped = 0
        self.state = "ok"
        self._writer: McapLogWriter | None = None
        self._largest_message = 0
        self._next_space_check = 0.0
        self._next_retry = 0.0
        self._space_state = "ok"
        self._closed = False
        self._in_frame = False
        self._opened = 0

    # ------------------------------------------------------------------ files
    @property
    def files_opened(self) -> int:
        return self._opened

    @property
    def current_path(self) -> Path | None:
        return self._writer.path if self._writer is not None else None

    def open(self) -> RotatingLog:
        """Create the first file. LogError when it cannot be (the run should not start), except
        for a full disk (ENOSPC, EDQUOT): that is counted and retried like a mid-run error, so a
        service whose disk is full still detects."""
        self._check_space(force=True)
        try:
            self._open_next()
        except LogError as exc:
            if getattr(exc.__cause__, "errno", None) not in (errno.ENOSPC, errno.EDQUOT):
                raise
            self._count(exc)
            self._next_retry = self._clock() + self.rotation.retry_interval_s
        self._update_state()
        return self

    def _open_next(self) -> None:
        """Open the next file of the set (LogError on failure), after trimming the set to the
        budget (first: on a full disk, deleting our oldest files is what makes room)."""
        self._trim()

        def open_file(path: Path, opened_ns: int):
            meta = {"run_started_ns": self.run_started_ns, "index": self._opened + 1,
                    "opened_ns": opened_ns, "previous": self.files[-1].name if self.files else None}
            try:
                return self._factory(path, self.config, manifest=self.manifest, run_config=self.run_config,
                                     extra_metadata={LOG_FILE_METADATA: meta}, exclusive=True)
            except LogError as exc:
                if not isinstance(exc.__cause__, FileExistsError) and path.exists() and not path.is_symlink():
                    try:  # created by us just now: don't leave debris
                        path.unlink()
                    except OSError:
                        pass
                raise

        path, self._writer = self.set.create_next(open_file)
        self._opened += 1
        self.files = [*self.files[-(MAX_LISTED_FILES - 1):], path]

    def _trim(self) -> None:
        budget = self.rotation.budget_mb
        if budget is None:
            return
        if self.rotation.max_mb is not None:
            reserve = int(self.rotation.max_mb * MB)
        else:
            reserve = self._writer.bytes_written if self._writer is not None else 0
        gone = self.set.trim_to_budget(int(budget * MB), reserve, self.current_path)
        self.deleted = [*self.deleted, *(f.path for f in gone)][-MAX_LISTED_FILES:]
        self.deleted_count += len(gone)

    def _rotate_if_full(self) -> None:
        if self.rotation.max_mb is None or self._writer is None or self._in_frame:
            return  # (never between a frame's image and its result: each file replays on its own)
        reserve = self.config.chunk_size + self._largest_message + self.rotation.summary_reserve_bytes
        if self._writer.bytes_written + reserve < self.rotation.max_mb * MB:
            return
        writer, self._writer = self._writer, None
        try:
            writer.close()
        except LogError as exc:
            self._count(exc)
            writer.abort()
            self._next_retry = self._clock() + self.rotation.retry_interval_s
            return
        self._open_next()

    # ------------------------------------------------------------------ state
    def _check_space(self, force: bool = False) -> None:
        now = self._clock()
        if not force and now < self._next_space_check:
            return
        self._next_space_check = now + self.rotation.space_check_interval_s
        try:
            free = self._free_space(self.set.directory)
        except OSError:
            return  # unknown: keep the last state
        if free < self.rotation.results_threshold_bytes:
            self._space_state = "stopped"
        elif free < self.rotation.images_threshold_bytes:
            self._space_state = "images_stopped"
        else:
            self._space_state = "ok"
        if self.rotation.max_mb is None and self._writer is not None and not force:
            self._trim()  # files not rotated: older files of the set make room as this one grows

    def _count(self, exc: Exception) -> None:
        self.errors += 1
        self.last_error = str(exc)[:200]

    def _update_state(self) -> None:
        if self._closed:
            self.state = "closed"
        elif self._writer is None:
            self.state = "failed"
        else:
            self.state = self._space_state

    def _ready(self, image: bool) -> McapLogWriter | None:
        """The writer to log to now, or None (message skipped: no space, or no file)."""
        if self._closed:
            return None
        self._check_space()
        if self._space_state == "stopped" or (image and self._space_state == "images_stopped"):
            self._update_state()
            return None
        try:
            self._rotate_if_full()
            if self._writer is None and self._clock() >= self._next_retry:
                self._open_next()
        except LogError as exc:
            self._count(exc)
            self._next_retry = self._clock() + self.rotation.retry_interval_s
        self._update_state()
        return self._writer

    def _write(self, image: bool, size: int, fn: Callable[[McapLogWriter], object]) -> bool:
        writer = self._ready(image)
        if writer is None:
            if image:
                self.images_skipped += 1
            else:
                self.messages_skipped += 1
            return False
        self._largest_message = max(self._largest_message, size)
        try:
            return bool(fn(writer))
        except LogError as exc:
            self._count(exc)
            if isinstance(exc.__cause__, OSError):  # the file is broken: abandon it, retry later
                writer.abort()
                self._writer = None
                self._next_retry = self._clock() + self.rotation.retry_interval_s
                self._update_state()
            return False

    # ------------------------------------------------------------------ writing (McapLogWriter's interface)
    def write_image(self, payload: bytes, encoding: str, stamp_ns: int, *, sequence: int = 0,
                    log_time_ns: int | None = None, gray=None) -> bool:
        """Log a frame image (see McapLogWriter.write_image); False when not logged."""
        self._in_frame = False  # a new frame: the file may be rotated before its image

        def write(w: McapLogWriter) -> bool:
            done = w.write_image(payload, encoding, stamp_ns, sequence=sequence, log_time_ns=log_time_ns, gray=gray)
            self.images_written += int(done)
            return done

        # A raw frame is stored as PNG, smaller than its pixels: len(payload) bounds the message.
        written = self._write(True, len(payload), write)
        self._in_frame = True  # the frame's result follows: it goes into the same file
        return written

    def write_result(self, result, *, data: bytes | None = None, log_time_ns: int | None = None) -> None:
        """Log a frame's result (see McapLogWriter.write_result), in the file of its image."""
        self._write(False, len(data or b""),
                    lambda w: w.write_result(result, data=data, log_time_ns=log_time_ns) or True)
        self._in_frame = False

    def write_view(self, topic: str, data: bytes, stamp_ns: int, *, sequence: int | None = None,
                   log_time_ns: int | None = None) -> bool:
        """Log a live-view message (see McapLogWriter.write_view), in the file of its frame;
        skipped like images when disk space is low."""
        in_frame = self._in_frame
        done = self._write(True, len(data),
                           lambda w: w.write_view(topic, data, stamp_ns, sequence=sequence, log_time_ns=log_time_ns))
        self._in_frame = in_frame
        return done

    def write_stats(self, stats, *, data: bytes | None = None, log_time_ns: int | None = None,
                    diagnostics: bytes | None = None) -> None:
        """Log a stats message (see McapLogWriter.write_stats: ``diagnostics``, the published ones)."""
        self._write(False, len(data or b"") + len(diagnostics or b""),
                    lambda w: w.write_stats(stats, data=data, log_time_ns=log_time_ns, diagnostics=diagnostics)
                    or True)

    def close(self) -> None:
        """Finish the open file; idempotent. An error finishing it is counted, not raised."""
        if self._closed:
            return
        self._closed = True
        writer, self._writer = self._writer, None
        if writer is not None:
            try:
                writer.close()
            except LogError as exc:
                self._count(exc)
                writer.abort()
        self._update_state()

    def __enter__(self) -> RotatingLog:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()
