"""The compiled kernels' build (everything else is in pyproject.toml).

runtime/core/native.py loads the library with ctypes: plain C, no Python API. Optional: where no
C compiler is found the install still succeeds and the numpy / OpenCV fallbacks run.
-ffp-contract=off: no fused multiply-add, so float results equal numpy's.
"""

from setuptools import Extension, setup

setup(ext_modules=[Extension("aefabmap.runtime.core._kernels", ["runtime/core/native/kernels.c"],
                             extra_compile_args=["-O3", "-ffp-contract=off"], optional=True)])
