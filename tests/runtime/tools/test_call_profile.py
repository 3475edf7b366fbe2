"""runtime/aefabmap_runtime/tools/call_profile.py: which library a profiled call belongs to, and the CPU seconds in them."""

from __future__ import annotations

import cv2
import numpy as np

from aefabmap_runtime.tools.call_profile import GROUPS, group_of, seconds_in_calls


def test_group_of_names_the_library_of_a_call():
    assert group_of(("~", 0, "<method 'detectAndCompute' of 'cv2.Feature2D' objects>")) == "opencv_features"
    assert group_of(("~", 0, "<method 'knnMatch' of 'cv2.DescriptorMatcher' objects>")) == "opencv_matching"
    assert group_of(("~", 0, "<batchDistance>")) == "opencv_matching"
    assert group_of(("~", 0, "<method 'apply' of 'cv2.CLAHE' objects>")) == "opencv_image"
    assert group_of(("~", 0, "<findFundamentalMat>")) == "opencv_fits"
    assert group_of(("~", 0, "<findHomography>")) == "opencv_fits"
    assert group_of(("~", 0, "<imdecode>")) == "opencv_image"
    assert group_of(("~", 0, "<resize>")) == "opencv_image"
    assert group_of(("~", 0, "<built-in method onnxruntime.capi.onnxruntime_pybind11_state.run>")) == "onnxruntime"
    assert group_of(("/x/aefabmap_runtime/core/kernels/native.py", 115, "nearest_two")) == "native_kernels"
    # Python: argument checks of the kernels, numpy, everything else.
    assert group_of(("/x/aefabmap_runtime/core/kernels/native.py", 78, "_arg")) is None
    assert group_of(("~", 0, "<built-in method numpy.fromiter>")) is None
    assert group_of(("~", 0, "<method 'reduce' of 'numpy.ufunc' objects>")) is None
    assert group_of(("/x/aefabmap_runtime/core/features/features.py", 238, "_pack")) is None


def test_seconds_in_calls_counts_the_opencv_call_not_the_python_around_it():
    image = np.random.default_rng(0).integers(0, 256, (480, 640), np.uint8)
    orb = cv2.ORB_create(500)

    def work():
        for _ in range(5):
            orb.detectAndCompute(image, None)
        sum(i * i for i in range(200_000))  # Python only

    seconds = seconds_in_calls(work)
    assert set(seconds) == set(GROUPS)
    assert seconds["opencv_features"] > 0
    assert seconds["opencv_fits"] == seconds["opencv_matching"] == seconds["onnxruntime"] == seconds["native_kernels"] == 0
