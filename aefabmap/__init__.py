"""aefabmap: appearance-based loop-closure detection (FAB-MAP 2.0) for small robots.

Library use::

    from aefabmap import DetectorConfig, default_bundle, load_detector
    detector = load_detector("bundles/orb_kmeans_3000", DetectorConfig())  # or default_bundle()
    result = detector.process(gray_image)      # a FrameResult; result.verified, result.verified_frame

The names below load lazily, so ``import aefabmap`` stays cheap for the CLI; none of them imports
zenoh, mcap, torch or onnx.
"""

from __future__ import annotations

import importlib
from importlib import resources
from pathlib import Path

from aefabmap_runtime.errors import (
    AefabmapError,
    BundleError,
    ConfigError,
    DataNotFoundError,
    ImageDecodeError,
    InputError,
    LogError,
    StateError,
    TransportError,
)
from aefabmap_runtime.version import __version__

# public name -> module that owns it
_LAZY = {
    "LoopClosureDetector": "aefabmap_runtime.core.detector",
    "DetectorConfig": "aefabmap_runtime.core.detector",
    "CandidateConfig": "aefabmap_runtime.core.decide.candidates",
    "VerificationConfig": "aefabmap_runtime.core.verify.verification",
    "RunConfig": "aefabmap_runtime.core.run_config",
    "FrameResult": "aefabmap_runtime.core.records.messages",
    "Candidate": "aefabmap_runtime.core.records.messages",
    "load_detector": "aefabmap_runtime.adapters.bundle_reader",
    "load_bundle": "aefabmap_runtime.adapters.bundle_reader",
    "FabMap2": "aefabmap_runtime.core.rank.fabmap",
    "Localization": "aefabmap_runtime.core.rank.fabmap",
    "ChowLiuTree": "aefabmap_runtime.core.rank.tree",
}


def default_bundle() -> Path:
    """The model bundle shipped in the package (ORB, 500 words, trained on synthetic worlds; see
    aefabmap/data/README.md), wherever the package is installed: pass it to load_detector."""
    return Path(str(resources.files(__name__) / "data" / "default_bundle"))


def __getattr__(name: str):
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'aefabmap' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(__all__)


__all__ = [
    "AefabmapError",
    "BundleError",
    "Candidate",
    "CandidateConfig",
    "ChowLiuTree",
    "ConfigError",
    "DataNotFoundError",
    "DetectorConfig",
    "FabMap2",
    "FrameResult",
    "ImageDecodeError",
    "InputError",
    "Localization",
    "LogError",
    "LoopClosureDetector",
    "RunConfig",
    "StateError",
    "TransportError",
    "VerificationConfig",
    "__version__",
    "default_bundle",
    "load_bundle",
    "load_detector",
]
