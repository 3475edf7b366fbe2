"""Scatter-add of per-word weights over place postings: the inner loop of FAB-MAP scoring (pure).

scores[p] = defaults[p] + sum of weights[i] over the rows i that hold a posting of p.

Two implementations with bit-identical results (each place's terms are summed in the same
order, defaults first, then row after row, no reassociation):
- numpy: one ``np.bincount`` over the defaults and the concatenated rows (always available);
- compiled: a plain loop compiled by numba when numba is installed (optional; about twice as
  fast per posting, and it needs no int64 copy of the ids nor a repeated-weights array).
"""

from __future__ import annotations

import numpy as np

try:  # optional: the numpy path gives the same numbers
    import numba as _numba
except ImportError:  # pragma: no cover - depends on the environment
    _numba = None

_kernel = None
_use_compiled = _numba is not None


def compiled_available() -> bool:
    """True when numba is installed (the compiled kernel can be used)."""
    return _numba is not None


def use_compiled(flag: bool) -> bool:
    """Choose the compiled kernel (when available) or numpy; returns the previous choice."""
    global _use_compiled
    previous = _use_compiled
    _use_compiled = bool(flag) and _numba is not None
    return previous


def active() -> str:
    """The implementation in use: "compiled" or "numpy"."""
    return "compiled" if _use_compiled else "numpy"


def prepare() -> None:
    """Compile the kernel now if it is in use (once per process, under a second), so that the
    first query does not pay for it."""
    if _use_compiled:
        _get_kernel()


def _get_kernel():
    """Compile the kernel on first use (once per process)."""
    global _kernel
    if _kernel is None:
        def scatter(acc, ids, weights, lens):
            pos = 0
            for i in range(lens.size):
                w = weights[i]
                for j in range(pos, pos + lens[i]):
                    acc[ids[j]] += w
                pos += lens[i]

        _kernel = _numba.njit("void(float64[::1], int32[::1], float64[::1], int64[::1])",
                              nogil=True, cache=False, boundscheck=False)(scatter)
    return _kernel


def scatter_scores(defaults: np.ndarray, rows: list[np.ndarray], weights: np.ndarray, lens: np.ndarray) -> np.ndarray:
    """defaults (n,) float64 plus the weights of each place's postings, shape (n,).

    rows: int32 posting arrays (place ids in [0, n)), row i receiving weights[i] (float64);
    lens: int64, lens[i] = len(rows[i]).
    """
    n = defaults.size
    total = int(lens.sum()) if lens.size else 0
    if total == 0:
        return defaults.copy()
    if _use_compiled:
        acc = defaults.copy()
        ids = rows[0] if len(rows) == 1 else np.concatenate(rows)
        _get_kernel()(acc, np.ascontiguousarray(ids, np.int32), np.ascontiguousarray(weights, np.float64),
                      np.ascontiguousarray(lens, np.int64))
        return acc
    ids = np.empty(n + total, np.intp)
    ids[:n] = np.arange(n, dtype=np.intp)
    # Concatenating straight into the intp buffer widens int32 postings in the same pass.
    np.concatenate(rows, out=ids[n:])
    w = np.empty(n + total, np.float64)
    # Defaults first: each place's sum then runs in the order of ``acc = defaults; acc[row] += w``.
    w[:n] = defaults
    w[n:] = np.repeat(weights, lens)
    return np.bincount(ids, w, minlength=n)
