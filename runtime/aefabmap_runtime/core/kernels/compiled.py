"""Compiled kernels: which can run here, and the switch between them and their numpy / OpenCV
fallbacks (the one place that imports numba).

Kernels (the FAB-MAP scatter in runtime/aefabmap_runtime/core/rank/scatter.py, the Hamming nearest-neighbour search in
runtime/aefabmap_runtime/core/kernels/bits.py, same-word matching in runtime/aefabmap_runtime/core/verify/word_matches.py, the count of distinct
matches in runtime/aefabmap_runtime/core/verify/verification.py, the model errors in runtime/aefabmap_runtime/core/verify/model_errors.py, the
int8 search's re-rank in runtime/aefabmap_runtime/core/words/bit_centroids.py) have two compiled forms and a fallback:

- "native": ahead-of-time compiled C (runtime/aefabmap_runtime/core/kernels/native.py), built when the package is
  installed; plain machine code, so it also runs under MemoryDenyWriteExecute=yes (the board
  unit, deploy/aefabmap.service). The default where it is built.
- "numba": the JIT (extra `fast`), compiled on first use or by `prepare`; numba fails to import
  where its JIT cannot map executable memory, and is then simply not offered.
- "numpy": numpy / OpenCV, always there.

Every form gives the same results (the model errors: to float64 rounding), so the choice changes
speed only.
"""

from __future__ import annotations

from types import ModuleType
from typing import Callable

from aefabmap_runtime.errors import ConfigError
from aefabmap_runtime.core.kernels import native

# numba is imported only when it may run a kernel: where the native library is in use, a process
# never pays for importing it (start-up time and resident memory on a board).
_numba: ModuleType | None = None
_numba_unavailable: str | None = None  # why numba cannot run here ("" when it can; None: not tried yet)


def _load_numba() -> ModuleType | None:
    """The numba module, imported on the first call (None where it cannot run here)."""
    global _numba, _numba_unavailable
    if _numba_unavailable is None:
        try:
            import numba as module
        except ImportError:  # pragma: no cover - depends on the environment
            module, _numba_unavailable = None, "numba is not installed (extra `fast`)"
        except Exception as exc:  # pragma: no cover - depends on the environment
            module, _numba_unavailable = None, f"numba cannot run here: {type(exc).__name__}: {exc}"
        else:
            _numba_unavailable = ""
        _numba = module
    return _numba


def __getattr__(name: str):
    """`compiled.numba`: the numba module (None where it cannot run), imported on first use."""
    if name == "numba":
        return _load_numba()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


#: What a benchmark or a test may ask for: "auto" (the preferred compiled form here), or a form.
KERNEL_CHOICES = ("auto", "native", "numba", "numpy")


def _forms():
    """The compiled forms that can run here, preferred first, found one at a time (numba is
    imported only when asked whether it runs)."""
    if native.available():
        yield "native"
    if _load_numba() is not None:
        yield "numba"


def backends() -> list[str]:
    """The compiled forms that can run here, preferred first (imports numba to find out)."""
    return list(_forms())


def _preferred() -> str:
    return next(_forms(), "numpy")


_use = _preferred()


def available() -> bool:
    """True when some compiled form can run here."""
    return next(_forms(), None) is not None


def unavailable_reason() -> str:
    """Why no compiled form can be used here ("" when one can)."""
    if available():
        return ""
    return f"{native.unavailable_reason()}; {_numba_unavailable or ''}"


def use(choice: bool | str) -> str:
    """Run the compiled kernels (True: the preferred form; or "native" / "numba", which must be
    available) or the fallbacks (False or "numpy"); returns the previous choice (a backend name,
    which `use` takes back)."""
    global _use
    previous = _use
    if choice is True:
        _use = _preferred()
    elif choice is False or choice == "numpy":
        _use = "numpy"
    elif choice in backends():
        _use = choice
    else:
        raise ConfigError(f"compiled kernels {choice!r} cannot run here (available: {backends() or 'none'}; "
                          f"{native.unavailable_reason() or _numba_unavailable or ''})")
    return previous


def active() -> str:
    """Whether the kernels run compiled: "compiled" or "numpy"."""
    return "numpy" if _use == "numpy" else "compiled"


def backend() -> str:
    """The form in use: "native", "numba" or "numpy"."""
    return _use


def describe() -> str:
    """One line for a log: the form in use, and why no compiled form runs when none can."""
    if _use == "numpy":
        return f"numpy / OpenCV ({unavailable_reason() or 'chosen'})"
    return "native (compiled ahead of time)" if _use == "native" else "numba (JIT)"


def kernel(native_form: Callable) -> Callable[[Callable[[], Callable]], Callable[[], Callable]]:
    """Decorator of a numba kernel's builder: a getter that returns native_form when "native" is in
    use, else the numba function the builder returns (compiled on the first call, then kept)."""
    def wrap(build: Callable[[], Callable]) -> Callable[[], Callable]:
        built: list[Callable] = []

        def get() -> Callable:
            if _use == "native":
                return native_form
            if not built:
                built.append(build())
            return built[0]

        return get

    return wrap


def prepare(*kernels: Callable[[], Callable]) -> None:
    """Compile the given kernels (`kernel` getters) now if numba is in use (far longer than a
    frame, once per process; docs/results.md, "Per frame"), so that the first frame does not pay
    for it. A JIT that imports but cannot compile here is dropped: the process goes on with the
    native form, or the fallbacks."""
    global _numba, _use, _numba_unavailable
    if _use != "numba":
        return
    try:
        for get in kernels:
            get()
    except Exception as exc:  # pragma: no cover - a JIT that imports but cannot compile here
        _numba = None
        _numba_unavailable = f"numba cannot compile here: {type(exc).__name__}: {exc}"
        _use = _preferred()
