"""Optional compiled kernels (numba): whether they can run here, and the switch between them
and their numpy / OpenCV fallbacks (the one place that imports numba).

Kernels (the FAB-MAP scatter in runtime/core/scatter.py, the Hamming nearest-neighbour search in
runtime/core/bits.py) register a builder with `kernel`; each is compiled on first use, or by
`prepare` ahead of the first frame. Every kernel has a fallback that gives the same results, so
the choice changes speed only.

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
_builders: list[Callable[[], Callable]] = []
_built: dict[int, Callable] = {}


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
    """Register `build` (returns a numba-compiled function; called only when numba imported) and
    return a getter that compiles it on first call and then returns it."""
    index = len(_builders)
    _builders.append(build)

    def get() -> Callable:
        fn = _built.get(index)
        if fn is None:
            fn = _built[index] = build()
        return fn

    return get


def prepare() -> None:
    """Compile every registered kernel now if compiled kernels are in use (about a second each,
    once per process), so that the first frame does not pay for it. A JIT that imports but
    cannot compile here switches the process to the fallbacks."""
    global numba, _use, _unavailable
    if not _use:
        return
    try:
        for index, build in enumerate(_builders):
            if index not in _built:
                _built[index] = build()
    except Exception as exc:  # pragma: no cover - a JIT that imports but cannot compile here
        numba, _use = None, False
        _unavailable = f"numba cannot compile here: {type(exc).__name__}: {exc}"
