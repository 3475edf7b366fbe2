"""Files that survive a crash and refuse what is not a file: the helpers the state directory
(state_dir.py) and its journal (map_journal.py) share; `log repair` (log_repair.py) opens its
input with open_regular too."""

from __future__ import annotations

import os
import stat
from pathlib import Path

from aefabmap_runtime.errors import AefabmapError, StateError


def fsync_dir(path: Path) -> None:
    """Make a directory's entries (a rename, a new file) durable."""
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def open_regular(path: Path, *, follow_symlinks: bool = False,
                 error: type[AefabmapError] = StateError) -> int:
    """A read-only descriptor of the regular file at `path` (a symlink is not followed unless
    `follow_symlinks`). OSError as open() raises it; `error` for a FIFO, device, socket or
    directory, refused without blocking (a FIFO with no writer would hang a plain open, a
    device read never ends)."""
    flags = os.O_RDONLY | os.O_NONBLOCK | (0 if follow_symlinks else os.O_NOFOLLOW)
    fd = os.open(path, flags)
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            raise error(f"{path} is not a regular file")
        os.set_blocking(fd, True)
    except BaseException:
        os.close(fd)
        raise
    return fd
