"""Loading untrusted .npy files: the header is checked before any array is allocated.

``np.load`` trusts the header: a 100-byte file claiming shape (10**12,) makes it try to
allocate terabytes (MemoryError, or the OOM killer on a board). :func:`load_npy` reads the
header first and refuses a dtype kind, shape or size that does not fit, with one message.
"""

from __future__ import annotations

import os
from typing import BinaryIO

import numpy as np

from aefabmap_runtime.errors import AefabmapError, InputError


def load_npy(
    fh: BinaryIO,
    label: str,
    *,
    kinds: str = "biuf",
    shape: tuple | None = None,
    error: type[AefabmapError] = InputError,
) -> np.ndarray:
    """Load a .npy from ``fh`` (a binary file at offset 0, no pickles) after checking its header.

    label: names the file in messages (e.g. ``"ground truth gt.npy"``).
    kinds: accepted numpy dtype kinds ("b" bool, "i"/"u" integers, "f" floats).
    shape: expected shape; None entries match any length (``(None,)``: any 1-D array).
    The header's shape times the item size must equal the bytes stored after it, so the load
    never allocates more than the file holds. Raises ``error`` (an aefabmap error class).
    """
    try:
        version = np.lib.format.read_magic(fh)
        if version == (1, 0):
            got_shape, _fortran, dtype = np.lib.format.read_array_header_1_0(fh)
        elif version == (2, 0):
            got_shape, _fortran, dtype = np.lib.format.read_array_header_2_0(fh)
        else:
            raise ValueError(f".npy format version {version} is not supported")
        data_bytes = os.fstat(fh.fileno()).st_size - fh.tell()
    except (OSError, ValueError, SyntaxError) as exc:
        raise error(f"{label}: not a readable .npy file: {exc}") from None
    if dtype.hasobject or dtype.kind not in kinds:
        raise error(f"{label} has dtype {dtype}, expected kind {kinds!r}")
    if shape is not None and (
        len(got_shape) != len(shape) or any(e is not None and g != e for g, e in zip(got_shape, shape))
    ):
        expected = "(" + ", ".join("N" if e is None else str(e) for e in shape) + ("," if len(shape) == 1 else "") + ")"
        raise error(f"{label} has shape {got_shape}, expected {expected}")
    n_bytes = dtype.itemsize
    for d in got_shape:
        n_bytes *= d
    if n_bytes != data_bytes:
        raise error(f"{label}: header says shape {got_shape} ({n_bytes} bytes) but the file holds {data_bytes} bytes")
    fh.seek(0)
    try:
        return np.load(fh, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise error(f"{label}: cannot read array: {exc}") from exc
