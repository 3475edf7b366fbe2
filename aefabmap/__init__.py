"""aefabmap: appearance-based loop-closure detection (FAB-MAP 2.0) for small robots."""

__version__ = "0.1.0"

from aefabmap.errors import (  # noqa: E402
    AefabmapError,
    BundleError,
    ConfigError,
    ImageDecodeError,
    InputError,
    LogError,
    TransportError,
)
from aefabmap.runtime.core.fabmap import FabMap2, Localization  # noqa: E402
from aefabmap.runtime.core.tree import ChowLiuTree  # noqa: E402

__all__ = [
    "AefabmapError",
    "BundleError",
    "ChowLiuTree",
    "ConfigError",
    "FabMap2",
    "ImageDecodeError",
    "InputError",
    "Localization",
    "LogError",
    "TransportError",
    "__version__",
]
