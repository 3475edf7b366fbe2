"""The map's state as plain arrays and scalars, and the checks that read it back (pure).

Each stateful part of the detector (place index, keypoint store, temporal filter, the
detector's own tables) has ``state() -> MapState`` and ``load_state(MapState)``. A state
read from disk is hostile input: every array is checked here (dtype kind, shape, bounds)
before any of it is used, and a failed check raises StateError naming the array. The file
format lives in runtime/aefabmap_runtime/adapters/state_dir.py.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from aefabmap_runtime.errors import StateError

Scalar = int | float | str | bool | None


@dataclass
class MapState:
    """Named numpy arrays plus JSON-able scalars. Names are dotted paths ("scorer.alive").

    deferred: (prefix, packer) pairs whose arrays are built later by ``resolve()``: a part whose
    contents are immutable once stored (the keypoint records) is captured as references when
    the state is taken and packed into arrays by whoever writes it (possibly another thread),
    so taking a state between two frames stays cheap.
    """

    arrays: dict[str, np.ndarray] = field(default_factory=dict)
    scalars: dict[str, Scalar] = field(default_factory=dict)
    deferred: list[tuple[str, Callable[[], MapState]]] = field(default_factory=list)

    def put(self, prefix: str, part: MapState) -> None:
        """Nest another part's state under ``prefix.`` (an empty prefix merges it as is)."""
        pre = f"{prefix}." if prefix else ""
        self.arrays.update({f"{pre}{k}": v for k, v in part.arrays.items()})
        self.scalars.update({f"{pre}{k}": v for k, v in part.scalars.items()})
        self.deferred.extend((f"{pre}{p}" if p else prefix, fn) for p, fn in part.deferred)

    def resolve(self) -> MapState:
        """Build the deferred arrays (in place); returns self."""
        while self.deferred:
            prefix, packer = self.deferred.pop(0)
            self.put(prefix, packer().resolve())
        return self

    def part(self, prefix: str) -> MapState:
        """The names under ``prefix.``, with the prefix removed."""
        p = prefix + "."
        return MapState(
            {k[len(p):]: v for k, v in self.arrays.items() if k.startswith(p)},
            {k[len(p):]: v for k, v in self.scalars.items() if k.startswith(p)},
        )

    def array(self, name: str, kinds: str, shape: tuple, *, lo: int | None = None, hi: int | None = None,
              as_int64: bool = True) -> np.ndarray:
        """The array ``name``, checked: dtype kind in ``kinds``, ``shape`` (None = any length),
        integer values in [lo, hi) when given. Integer arrays come back as int64 unless
        ``as_int64`` is False (bulk arrays such as descriptors keep their compact type)."""
        a = self.arrays.get(name)
        if a is None:
            raise StateError(f"map state has no array {name!r}")
        a = np.asarray(a)
        if a.dtype.kind not in kinds or a.dtype.hasobject:
            raise StateError(f"map state array {name!r} has dtype {a.dtype}, expected kind {kinds!r}")
        if a.ndim != len(shape) or any(e is not None and g != e for g, e in zip(a.shape, shape)):
            raise StateError(f"map state array {name!r} has shape {a.shape}, expected {_shape_text(shape)}")
        if a.dtype.kind in "iu":
            if a.size and lo is not None and int(a.min()) < lo:
                raise StateError(f"map state array {name!r} holds {int(a.min())} < {lo}")
            if a.size and hi is not None and int(a.max()) >= hi:
                raise StateError(f"map state array {name!r} holds {int(a.max())}, expected < {hi}")
            if as_int64:
                a = a.astype(np.int64)
        elif a.dtype.kind == "f" and not np.isfinite(a).all():
            raise StateError(f"map state array {name!r} holds NaN or infinite values")
        return a

    def scalar(self, name: str, kind: type | tuple, *, lo: int | None = None, hi: int | None = None):
        """The scalar ``name`` of type ``kind`` (bool is never taken for int), optionally in [lo, hi)."""
        if name not in self.scalars:
            raise StateError(f"map state has no value {name!r}")
        v = self.scalars[name]
        kinds = kind if isinstance(kind, tuple) else (kind,)
        if not isinstance(v, kinds) or (isinstance(v, bool) and bool not in kinds):
            raise StateError(f"map state value {name!r} is {str(v)[:40]!r}, expected {'/'.join(k.__name__ for k in kinds)}")
        if isinstance(v, int) and not isinstance(v, bool) and (
            (lo is not None and v < lo) or (hi is not None and v >= hi)
        ):
            raise StateError(f"map state value {name!r} = {v} is outside [{lo}, {hi})")
        return v


def _shape_text(shape: tuple) -> str:
    return "(" + ", ".join("N" if e is None else str(e) for e in shape) + ("," if len(shape) == 1 else "") + ")"


def pack_ragged(rows: list[np.ndarray | None], dtype) -> tuple[np.ndarray, np.ndarray]:
    """Rows (None = empty) -> (ptr (n + 1,) int64, values concatenated as dtype)."""
    lengths = np.array([0 if r is None else len(r) for r in rows], np.int64)
    ptr = np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64)
    parts = [np.asarray(r) for r in rows if r is not None and len(r)]
    values = np.concatenate(parts).astype(dtype, copy=False) if parts else np.zeros(0, dtype)
    return ptr, values


def check_ptr(state: MapState, name: str, n_rows: int, n_values: int) -> np.ndarray:
    """A CSR pointer (n_rows + 1,) from 0 to n_values, non-decreasing."""
    ptr = state.array(name, "iu", (n_rows + 1,), lo=0, hi=n_values + 1)
    if ptr[0] != 0 or ptr[-1] != n_values or np.any(np.diff(ptr) < 0):
        raise StateError(f"map state array {name!r} is not a valid row pointer over {n_values} values")
    return ptr
