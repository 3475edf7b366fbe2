"""Scatter-add of per-word weights over place postings: the inner loop of FAB-MAP scoring (pure).

scores[p] = defaults[p] + sum of weights[i] over the rows i that hold a posting of p.

Two implementations with bit-identical results (each place's terms are summed in the same
order, defaults first, then row after row, no reassociation):
- numpy: one ``np.bincount`` over the defaults and the concatenated rows (always available);
- compiled: a plain loop, compiled ahead of time or by numba (runtime/aefabmap_runtime/core/kernels/compiled.py; faster per
  posting, and it needs no int64 copy of the ids nor a repeated-weights array; docs/results.md,
  "FAB-MAP inference and Chow-Liu learning").

The compiled loop (`scatter_buffers`) reads each row where it lies, from its data address:
PostingLists hands it the addresses of its word buffers, so at 100k places a query's millions
of postings are not copied end to end first (that copy was a large share of the scoring time:
CHANGELOG.md, "100k places in 4 ms with the compiled scatter");
`scatter_packed` hands it offsets into one array that holds all the rows (the new-place model's
static postings, `scatter_scores`'s concatenated rows).
"""

from __future__ import annotations

import functools

import numpy as np

from aefabmap_runtime.errors import ConfigError

from aefabmap_runtime.core.kernels import compiled, native


@functools.cache
def _int32_buffer_intrinsic():
    """numba's _int32_buffer(address): an integer data address -> int32* (indexable in compiled
    code; no bounds), for kernels built while numba is in use (it imports numba)."""
    from numba import types
    from numba.extending import intrinsic

    @intrinsic
    def _int32_buffer(typingctx, address):
        pointer = types.CPointer(types.int32)

        def codegen(context, builder, signature, args):
            return builder.inttoptr(args[0], context.get_value_type(pointer))

        return pointer(types.intp), codegen

    return _int32_buffer


@compiled.kernel(native.scatter_buffers)
def buffers_kernel():
    """The address-reading loop, compiled (runtime/aefabmap_runtime/core/kernels/compiled.py)."""
    _int32_buffer = _int32_buffer_intrinsic()

    def scatter(acc, addresses, weights, lens):
        for i in range(addresses.size):
            row = _int32_buffer(addresses[i])
            w = weights[i]
            for j in range(lens[i]):
                acc[row[j]] += w

    return compiled.numba.njit("void(float64[::1], intp[::1], float64[::1], int32[::1])",
                               nogil=True, cache=False, boundscheck=False)(scatter)


@compiled.kernel(native.append_postings)
def append_kernel():
    """One posting appended to each of several word buffers, compiled: buffer i (the int32 data
    at addresses[i]) gets `pid` at position positions[i] (the caller checked it has room)."""
    _int32_buffer = _int32_buffer_intrinsic()

    def append(addresses, positions, pid):
        for i in range(addresses.size):
            _int32_buffer(addresses[i])[positions[i]] = pid

    return compiled.numba.njit("void(intp[::1], int32[::1], int32)", nogil=True, cache=False,
                               boundscheck=False)(append)


def scatter_buffers(defaults: np.ndarray, addresses: np.ndarray, weights: np.ndarray, lens: np.ndarray) -> np.ndarray:
    """As `scatter_scores`, row i being lens[i] int32 place ids (each < defaults.size) at data
    address addresses[i] (intp); compiled kernel only (`compiled.active()` is "compiled").

    Reads raw memory: the caller guarantees every address is the data of a live C-contiguous
    int32 buffer of at least lens[i] entries for the duration of the call (PostingLists and
    `scatter_packed` do).
    """
    if compiled.active() != "compiled":
        raise ConfigError("scatter_buffers needs the compiled kernels (runtime/aefabmap_runtime/core/kernels/compiled.py) in use")
    acc = np.array(defaults, dtype=np.float64, copy=True)
    if lens.size:
        buffers_kernel()(acc, np.ascontiguousarray(addresses, np.intp), np.ascontiguousarray(weights, np.float64),
                              np.ascontiguousarray(lens, np.int32))
    return acc


def scatter_packed(defaults: np.ndarray, packed: np.ndarray, starts: np.ndarray, weights: np.ndarray,
                   lens: np.ndarray) -> np.ndarray:
    """As `scatter_buffers`, row i being the lens[i] place ids of `packed` (one int32 array) from
    offset starts[i]: the rows are read where they lie; compiled kernel only."""
    if packed.dtype != np.int32 or not packed.flags.c_contiguous:
        raise ConfigError("scatter_packed reads C-contiguous int32 postings")
    return scatter_buffers(defaults, packed.ctypes.data + packed.itemsize * np.asarray(starts, np.intp), weights, lens)


def scatter_scores(defaults: np.ndarray, rows: list[np.ndarray], weights: np.ndarray, lens: np.ndarray) -> np.ndarray:
    """defaults (n,) float64 plus the weights of each place's postings, shape (n,).

    rows: int32 posting arrays (place ids in [0, n)), row i receiving weights[i] (float64);
    lens: int64, lens[i] = len(rows[i]).
    """
    n = defaults.size
    total = int(lens.sum()) if lens.size else 0
    if total == 0:
        return defaults.copy()
    if compiled.active() == "compiled":
        ids = np.ascontiguousarray(rows[0] if len(rows) == 1 else np.concatenate(rows), np.int32)
        starts = np.cumsum(lens, dtype=np.intp) - lens  # row i starts starts[i] postings into ids
        return scatter_packed(defaults, ids, starts, weights, lens)
    ids = np.empty(n + total, np.intp)
    ids[:n] = np.arange(n, dtype=np.intp)
    # Concatenating straight into the intp buffer widens int32 postings in the same pass.
    np.concatenate(rows, out=ids[n:])
    w = np.empty(n + total, np.float64)
    # Defaults first: each place's sum then runs in the order of ``acc = defaults; acc[row] += w``.
    w[:n] = defaults
    w[n:] = np.repeat(weights, lens)
    return np.bincount(ids, w, minlength=n)
