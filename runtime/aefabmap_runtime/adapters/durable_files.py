"""Files that survive a crash and refuse what is not a file: the helpers the state directory
(state_dir.py) and its journal (map_journal.py) share."""

from __future__ import annotations

import os
import stat
from pathlib import Path

from aefabmap_runtime.errors import StateError


def fsync_dir(path: Path) -> None:
    """Make a directory's entries (a rename, a new file) durable."""
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def open_regular(path: Path) -> int:
    """A read-only descriptor of the regular file at `path` (not followed if a symlink). OSError
    as open() raises it; StateError for a FIFO, device, socket or directory, refused without
    blocking (a FIFO with no writer would hang a plain open, a device read never ends)."""
    fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            raise StateError(f"{path} is not a regular file")
        os.set_blocking(fd, True)
    except BaseException:
        os.close(fd)
        raise
    return fd
