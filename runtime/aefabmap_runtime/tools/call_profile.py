"""CPU time a run spends inside the compiled calls of each library (cProfile, CPU clock).

Groups (GROUPS) of the calls a frame makes:

- opencv_features: OpenCV's feature detectors and describers (``Feature2D`` methods: SIFT, and
  ORB where the compiled kernels do not detect and describe it);
- opencv_fits: OpenCV's two-view model fits (homography, fundamental and essential matrices);
- opencv_matching: OpenCV's descriptor distances (the numpy kernels' all-pairs matching);
- opencv_image: JPEG decoding and image preparation (any other OpenCV call);
- onnxruntime: graph runs (the int8 product of the flat search, the autoencoder);
- native_kernels: aefabmap's own compiled kernels (runtime/aefabmap_runtime/core/kernels/native.py).

The profiler slows Python down, not the compiled calls: their times hold for an unprofiled run,
and what such a run spends beyond them is Python and numpy.
"""

from __future__ import annotations

import cProfile
import pstats
import time
from collections.abc import Callable

GROUPS = ("opencv_features", "opencv_fits", "opencv_matching", "opencv_image", "onnxruntime", "native_kernels")
#: OpenCV functions that fit a two-view model, and those that compare descriptors.
FITS = frozenset({"findHomography", "findFundamentalMat", "findEssentialMat", "recoverPose"})
MATCHING = frozenset({"batchDistance", "norm"})
#: native.py helpers that check arguments in Python: not kernel time.
NATIVE_HELPERS = frozenset({"_arg", "_writable", "_same", "_memory", "_points", "_load"})


def group_of(key: tuple[str, int, str]) -> str | None:
    """The GROUPS name of one pstats key (file name, line, function name), None for the rest."""
    import cv2

    filename, _, name = key
    if filename == "~":  # a compiled (built-in) call
        if "of 'cv2.Feature2D'" in name:
            return "opencv_features"
        if "of 'cv2.DescriptorMatcher'" in name:
            return "opencv_matching"
        if "of 'cv2." in name:
            return "opencv_image"
        if "onnxruntime" in name:
            return "onnxruntime"
        bare = name.strip("<>")
        if bare in FITS:
            return "opencv_fits"
        if bare in MATCHING:
            return "opencv_matching"
        return "opencv_image" if bare.isidentifier() and hasattr(cv2, bare) else None
    if filename.replace("\\", "/").endswith("aefabmap_runtime/core/kernels/native.py") and name not in NATIVE_HELPERS:
        return "native_kernels"
    return None


def seconds_in_calls(fn: Callable[[], object]) -> dict[str, float]:
    """Run fn() under the profiler; CPU seconds spent in each of GROUPS' calls."""
    profiler = cProfile.Profile(time.process_time)
    profiler.runcall(fn)
    seconds = dict.fromkeys(GROUPS, 0.0)
    for key, (_, _, own_seconds, _, _) in pstats.Stats(profiler).stats.items():
        group = group_of(key)
        if group is not None:
            seconds[group] += own_seconds
    return seconds
