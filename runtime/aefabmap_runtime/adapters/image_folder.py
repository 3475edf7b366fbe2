"""Image folders as sequences: the files of a directory sorted by name (= temporal order)."""

from __future__ import annotations

from pathlib import Path

from aefabmap_runtime.errors import DataNotFoundError

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".ppm", ".pgm", ".bmp")


def list_images(directory: str | Path) -> list[Path]:
    """Image files of a directory sorted by name (= temporal order); raises when there are none."""
    d = Path(directory)
    if not d.is_dir():
        raise DataNotFoundError(f"image directory {d} does not exist")
    files = sorted(p for p in d.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())
    if not files:
        raise DataNotFoundError(f"no images ({', '.join(IMAGE_SUFFIXES)}) in {d}")
    return files
