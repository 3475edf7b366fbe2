"""What pyproject.toml cannot say: the source roots and the compiled kernels' build.

Source roots: each top-level folder holds its package under its own import name
(`runtime/aefabmap_runtime/` is `aefabmap_runtime`), so an import resolves to a file from its
dotted name alone; `aefabmap/` (the CLI, the SLAM tool, the public API) sits at the root.

The kernels: runtime/aefabmap_runtime/core/kernels/native.py loads the library with ctypes
(plain C, no Python API). Optional: where no C compiler is found the install still succeeds and
the numpy / OpenCV fallbacks run. -ffp-contract=off: no fused multiply-add, so float results
equal numpy's.
"""

from setuptools import Extension, find_namespace_packages, setup

#: package -> the folder that holds it.
ROOTS = {
    "aefabmap": "aefabmap",
    "aefabmap_runtime": "runtime/aefabmap_runtime",
    "aefabmap_trainer": "trainer/aefabmap_trainer",
    "aefabmap_export": "export/aefabmap_export",
}


def _packages() -> list[str]:
    found = []
    for name, folder in ROOTS.items():
        found += [name, *(f"{name}.{p}" for p in find_namespace_packages(folder, exclude=["*__pycache__*"]))]
    return found


setup(
    packages=_packages(),
    package_dir=ROOTS,
    ext_modules=[Extension("aefabmap_runtime.core.kernels._kernels", ["runtime/aefabmap_runtime/core/kernels/kernels.c"],
                           extra_compile_args=["-O3", "-ffp-contract=off"], optional=True)],
)
