"""Optional compiled kernels (numba): whether they can run here, and the switch between them
and their numpy / OpenCV fallbacks (the one place that imports numba).

Kernels (the FAB-MAP scatter in runtime/core/scatter.py, the Hamming nearest-neighbour search in
runtime/core/bits.py, same-word matching in runtime/core/word_matches.py, the count of distinct
matches in runtime/core/verification.py, the model errors in runtime/core/model_errors.py, the
int8 search's re-rank in runtime/core/bit_centroids.py) wrap their builder with `kernel`; each is
compiled on first use, or by `prepare` when its user is built (FAB-MAP its scatter, a verifying
detector its matchers and model errors, the int8 search its re-rank). Every kernel has a fallback
that gives the same results (the model errors: to float64 rounding), so the choice changes speed
only.

numba is the extra `fast`. It also fails to import where its JIT cannot map executable memory
(a systemd unit with MemoryDenyWriteExecute=yes, such as deploy/aefabmap.service): the runtime
then runs on the fallbacks instead of crashing.
"""

from __future__ import annotations

from typing import Callable

_unavailable = ""  # why compiled kernels cannot run here ("" when they can)
try:
    import numba
except ImportError:  # pragma: no cover - depends on the environment
    numba, _unavailable = None, "numba is not installed (extra `fast`)"
except Exception as exc:  # pragma: no cover - depends on the environment
    numba, _unavailable = None, f"numba cannot run here: {type(exc).__name__}: {exc}"

_use = numba is not None


def available() -> bool:
    """True when numba is installed and can compile here."""
    return numba is not None


def unavailable_reason() -> str:
    """Why compiled kernels cannot be used here ("" when they can)."""
    return _unavailable


def use(flag: bool) -> bool:
    """Run the compiled kernels (when available) or the fallbacks; returns the previous choice."""
    global _use
    previous = _use
    _use = bool(flag) and numba is not None
    return previous


def active() -> str:
    """The implementation in use: "compiled" or "numpy"."""
    return "compiled" if _use else "numpy"


def kernel(build: Callable[[], Callable]) -> Callable[[], Callable]:
    """A getter of the function `build` returns (numba-compiled; built only when numba imported):
    it compiles on the first call and then returns the same function."""
    built: list[Callable] = []

    def get() -> Callable:
        if not built:
            built.append(build())
        return built[0]

    return get


def prepare(*kernels: Callable[[], Callable]) -> None:
    """Compile the given kernels (`kernel` getters) now if compiled kernels are in use (far
    longer than a frame, once per process; docs/results.md, "Per frame"), so that the first frame
    does not pay for it. A JIT that imports
    but cannot compile here switches the process to the fallbacks."""
    global numba, _use, _unavailable
    if not _use:
        return
    try:
        for get in kernels:
            get()
    except Exception as exc:  # pragma: no cover - a JIT that imports but cannot compile here
        numba, _use = None, False
        _unavailable = f"numba cannot compile here: {type(exc).__name__}: {exc}"
