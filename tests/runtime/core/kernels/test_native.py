"""The ahead-of-time compiled kernels (runtime/aefabmap_runtime/core/kernels/native.py): found, checked, and never fed an
array they would read out of bounds; an install without them runs the fallbacks."""

from __future__ import annotations

import shutil
import subprocess
import sys

import numpy as np
import pytest

from aefabmap_runtime.errors import ConfigError
from aefabmap_runtime.core.kernels import compiled, native

needs_native = pytest.mark.skipif(not native.available(), reason=f"native kernels: {native.unavailable_reason()}")


@needs_native
@pytest.mark.parametrize(
    "call",
    [
        # a row width that disagrees with the transposed rows
        lambda: native.nearest_two(np.zeros((3, 4), np.uint64), np.zeros((3, 5), np.uint64),
                                   np.zeros((3, 2), np.int32), np.zeros((3, 2), np.int32)),
        # a wrong dtype: uint8 bytes where uint64 words are read
        lambda: native.nearest_two(np.zeros((3, 32), np.uint8), np.zeros((4, 5), np.uint64),
                                   np.zeros((3, 2), np.int32), np.zeros((3, 2), np.int32)),
        # a non-contiguous view
        lambda: native.nearest_two(np.zeros((3, 8), np.uint64)[:, ::2], np.zeros((4, 5), np.uint64),
                                   np.zeros((3, 2), np.int32), np.zeros((3, 2), np.int32)),
        # an output too short for the rows
        lambda: native.nearest_two(np.zeros((3, 4), np.uint64), np.zeros((4, 5), np.uint64),
                                   np.zeros((2, 2), np.int32), np.zeros((3, 2), np.int32)),
        # a sort order pointing past the place rows
        lambda: native.same_word(np.zeros(2, np.int64), np.zeros((2, 4), np.uint64), np.zeros(3, np.int64),
                                 np.array([0, 1, 7]), np.zeros((3, 4), np.uint64), 64.0, 0.8,
                                 np.zeros((2, 2), np.int64)),
        # weights and lengths of unequal length
        lambda: native.scatter_buffers(np.zeros(4), np.zeros(2, np.intp), np.zeros(3), np.zeros(2, np.int32)),
        # point arrays of unequal length
        lambda: native.epipolar_errors(np.eye(3), np.zeros((4, 2)), np.zeros((3, 2)), 1e-9, np.zeros(4)),
        # centroids of another dimension than the bits
        lambda: native.select_words(np.zeros((2, 3), np.int32), np.zeros(3, np.int32), np.zeros(3, np.int32),
                                    np.zeros((2, 8), np.uint8), np.zeros((3, 16), np.float32), np.zeros(3),
                                    np.zeros(2, np.int32)),
        # a read-only output
        lambda: native.transfer_errors(np.eye(3), np.eye(3), np.zeros((2, 2)), np.zeros((2, 2)),
                                       np.frombuffer(bytes(16))),
    ],
    ids=["width", "dtype", "strided", "short-output", "order", "lengths", "points", "centroids", "read-only"],
)
def test_arrays_that_would_be_read_out_of_bounds_are_refused(call):
    with pytest.raises(ConfigError):
        call()


def test_a_missing_library_leaves_the_fallbacks(tmp_path, monkeypatch):
    monkeypatch.setattr(native, "library_paths", lambda: [tmp_path / "_kernels.so"])
    lib, reason = native._load()
    assert lib is None and "not built" in reason


@pytest.mark.skipif(shutil.which("cc") is None, reason="needs a C compiler")
def test_a_library_of_another_version_is_not_used(tmp_path, monkeypatch):
    source = tmp_path / "k.c"
    stubs = "".join(f"void {name}(void) {{}}\n" for name in native._SIGNATURES if name != "aefabmap_kernels_version")
    source.write_text("long long aefabmap_kernels_version(void) { return 999; }\n" + stubs)
    built = tmp_path / "_kernels.so"
    subprocess.run(["cc", "-shared", "-fPIC", "-o", str(built), str(source)], check=True)
    monkeypatch.setattr(native, "library_paths", lambda: [built])
    lib, reason = native._load()
    assert lib is None and "another version" in reason


def test_asking_for_a_form_that_cannot_run_is_a_config_error(monkeypatch):
    monkeypatch.setattr(compiled, "_forms", lambda: iter(()))
    previous = compiled.backend()
    try:
        with pytest.raises(ConfigError, match="cannot run here"):
            compiled.use("native")
        assert compiled.use(True) == previous and compiled.backend() == "numpy"
    finally:
        monkeypatch.undo()
        compiled.use(previous)


@needs_native
def test_a_detector_on_the_native_kernels_never_imports_numba():
    """numba costs start-up time and resident memory: a process whose kernels are native leaves it out."""
    probe = ("import sys\nfrom aefabmap import default_bundle, load_detector\nimport numpy as np\n"
             "d = load_detector(default_bundle())\n"
             "d.process(np.random.default_rng(0).integers(0, 255, (240, 320), np.uint8))\n"
             "from aefabmap_runtime.core.kernels import compiled\n"
             "print(compiled.backend(), 'numba' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ["native", "False"]
