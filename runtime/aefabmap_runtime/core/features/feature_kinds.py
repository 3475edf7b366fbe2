"""Feature-kind registry: everything the pipeline knows about one descriptor type, in one place.

A kind declares
- its raw descriptors as the extractor returns them: `width` columns of `dtype`
  (binary kinds: uint8 bytes; float kinds: float32 values);
- `distance`: how two raw descriptors compare in matching ("hamming" or "l2");
- the *descriptor vectors* every quantiser consumes (`vectors`, float32 (N, vector_length)):
  binary kinds unpack their bytes to bits in {0, 1}, float kinds pass their values through.
  In that form squared L2 is the right quantiser distance for every kind (for bit vectors it
  equals the Hamming distance), so k-means and the nearest-centroid quantiser need no branch;
- `ae_scaling`: the autoencoder's [0,1] input scaling ("none" for bits, "minmax" for floats);
- `compress`: the uint8 store form of the keypoint store (`store_bytes` per descriptor);
- `create(max_features)`: the OpenCV extractor, and `finish(desc, options)`: what is done to
  its descriptors before anyone sees them (SIFT: L2 or RootSIFT normalisation);
- `options`: FeatureConfig flags the kind accepts (SIFT: "rootsift").

Adding a descriptor type (e.g. AKAZE's 61-byte binary descriptor) is one `register` call:
`register(BinaryKind("akaze", 61, lambda n: cv2.AKAZE_create()))`. Nothing downstream looks
at array shapes to guess the kind.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from aefabmap_runtime.errors import ConfigError, InputError

DISTANCES = ("hamming", "l2")


@dataclass(frozen=True)
class FeatureKind:
    """One registered descriptor type (see the module doc). Subclasses fix the descriptor family.

    name: manifest / CLI name. width: columns of a raw descriptor row.
    create: max_features -> an OpenCV Feature2D with detectAndCompute.
    options: names of the FeatureConfig flags this kind accepts.
    window_scale: radius of the image window a descriptor is computed from, in keypoint sizes
        (OpenCV's KeyPoint.size, a diameter): ORB samples its tests inside the keypoint's
        patch, so 0.5; SIFT's 4 x 4 histogram cells of 3 sigma each (size = 2 sigma), rotated,
        reach 3 * (size / 2) * sqrt(2) * (4 + 1) / 2 = 5.3 sizes. Verification counts matches
        whose windows mostly overlap as one piece of evidence (`VerificationConfig.independence`).
    upright: verification also describes this kind's keypoints with orientation 0
        (`Features.upright`, VerificationConfig.upright); its describer must turn its window by
        KeyPoint.angle and ignore KeyPoint.class_id (ORB's and SIFT's do; AKAZE keeps its scale
        level in class_id). On for ORB. Off for SIFT: a second SIFT description costs about 40 %
        of its extraction (docs/results.md, "Upright descriptors in the retry").
    """

    name: str
    width: int
    create: Callable[[int], Any]
    options: tuple[str, ...] = ()
    window_scale: float = 0.5
    upright: bool = False

    # Declared by the family (class attributes of the subclasses).
    dtype = np.dtype(np.uint8)
    distance = "hamming"
    ae_scaling = "none"

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name:
            raise ConfigError(f"feature kind name must be a non-empty string, got {self.name!r}")
        if not isinstance(self.width, int) or self.width < 1:
            raise ConfigError(f"feature kind {self.name}: width must be a positive integer, got {self.width!r}")
        if not (isinstance(self.window_scale, (int, float)) and 0 < self.window_scale < 100):
            raise ConfigError(f"feature kind {self.name}: window_scale must lie in (0, 100), got {self.window_scale!r}")

    def window_radius(self, sizes: np.ndarray) -> np.ndarray:
        """Radius of each keypoint's descriptor window (N,), in the units of `sizes` (N,)."""
        return np.asarray(sizes, np.float64) * self.window_scale

    @property
    def vector_length(self) -> int:
        """D of the descriptor vectors (what the manifest calls descriptor_length)."""
        raise NotImplementedError

    @property
    def store_bytes(self) -> int:
        """Bytes of one descriptor in the keypoint store."""
        raise NotImplementedError

    def empty(self) -> np.ndarray:
        """(0, width) raw descriptors of this kind."""
        return np.zeros((0, self.width), self.dtype)

    def check(self, descriptors: np.ndarray) -> np.ndarray:
        """Raise InputError unless descriptors are (N, width) raw descriptors of this kind."""
        raise NotImplementedError

    def finish(self, descriptors: np.ndarray, rootsift: bool = False) -> np.ndarray:
        """The extractor's descriptors (N, width) -> this kind's raw form (contiguous)."""
        raise NotImplementedError

    def vectors(self, descriptors: np.ndarray) -> np.ndarray:
        """Raw descriptors (N, width) -> float32 descriptor vectors (N, vector_length)."""
        raise NotImplementedError

    def compress(self, descriptors: np.ndarray) -> np.ndarray:
        """Raw descriptors (N, width) -> (N, store_bytes) uint8 store form."""
        raise NotImplementedError


@dataclass(frozen=True)
class BinaryKind(FeatureKind):
    """Binary descriptors: `width` uint8 bytes, Hamming distance, vectors are the unpacked bits."""

    dtype = np.dtype(np.uint8)
    distance = "hamming"
    ae_scaling = "none"

    @property
    def vector_length(self) -> int:
        return 8 * self.width

    @property
    def store_bytes(self) -> int:
        return self.width

    def check(self, descriptors: np.ndarray) -> np.ndarray:
        d = descriptors
        if not isinstance(d, np.ndarray) or d.dtype != np.uint8 or d.ndim != 2 or d.shape[1] != self.width:
            got = f"{d.shape} {d.dtype}" if isinstance(d, np.ndarray) else type(d).__name__
            raise InputError(f"{self.name.upper()} descriptors must be (N, {self.width}) uint8, got {got}")
        return d

    def finish(self, descriptors: np.ndarray, rootsift: bool = False) -> np.ndarray:
        return np.ascontiguousarray(descriptors, np.uint8)

    def vectors(self, descriptors: np.ndarray) -> np.ndarray:
        return np.unpackbits(self.check(descriptors), axis=1).astype(np.float32)

    def compress(self, descriptors: np.ndarray) -> np.ndarray:
        # Bytes are already as small as they get: stored as extracted.
        return np.ascontiguousarray(self.check(descriptors))


@dataclass(frozen=True)
class FloatKind(FeatureKind):
    """Float descriptors: `width` float32 values of unit L2 norm, L2 distance, vectors unchanged."""

    dtype = np.dtype(np.float32)
    distance = "l2"
    ae_scaling = "minmax"

    @property
    def vector_length(self) -> int:
        return self.width

    @property
    def store_bytes(self) -> int:
        return self.width

    def check(self, descriptors: np.ndarray) -> np.ndarray:
        d = descriptors
        if not isinstance(d, np.ndarray) or d.ndim != 2 or d.shape[1] != self.width or not np.issubdtype(d.dtype, np.number):
            got = f"{d.shape} {d.dtype}" if isinstance(d, np.ndarray) else type(d).__name__
            raise InputError(f"{self.name.upper()} descriptors must be (N, {self.width}) numbers, got {got}")
        return d

    def finish(self, descriptors: np.ndarray, rootsift: bool = False) -> np.ndarray:
        d = descriptors.astype(np.float32)
        if rootsift:
            # Hellinger kernel: L1-normalise, then square-root (the result has L2 norm 1).
            d = np.sqrt(d / np.maximum(d.sum(axis=1, keepdims=True), 1e-12))
        else:
            d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
        return np.ascontiguousarray(d)

    def vectors(self, descriptors: np.ndarray) -> np.ndarray:
        return np.ascontiguousarray(self.check(descriptors), dtype=np.float32)

    def compress(self, descriptors: np.ndarray) -> np.ndarray:
        """Per row, the largest component maps to 255 (L2 matching renormalises, so a per-row
        scale loses nothing but rounding: `width` bytes instead of 4 * `width`)."""
        d = np.asarray(self.check(descriptors), np.float32)
        peak = np.maximum(d.max(axis=1, keepdims=True), 1e-12)
        return np.clip(np.rint(d / peak * 255.0), 0, 255).astype(np.uint8)


_REGISTRY: dict[str, FeatureKind] = {}


def register(kind: FeatureKind) -> FeatureKind:
    """Make a kind available by name (FeatureConfig, bundles, CLI); names are unique."""
    if not isinstance(kind, FeatureKind) or type(kind) is FeatureKind:
        raise ConfigError("register a BinaryKind or FloatKind")
    if kind.distance not in DISTANCES:
        raise ConfigError(f"feature kind {kind.name}: distance must be one of {DISTANCES}")
    if kind.name in _REGISTRY:
        raise ConfigError(f"feature kind {kind.name!r} is already registered")
    _REGISTRY[kind.name] = kind
    return kind


def unregister(name: str) -> None:
    """Forget a registered kind (tests that register throwaway kinds); built-ins stay."""
    if name in BUILTIN_KINDS:
        raise ConfigError(f"built-in feature kind {name!r} cannot be unregistered")
    _REGISTRY.pop(name, None)


def get_kind(name: str) -> FeatureKind:
    """The registered kind called `name`; ConfigError naming the known ones otherwise."""
    try:
        return _REGISTRY[name]
    except (KeyError, TypeError):
        raise ConfigError(f"feature kind must be one of {kind_names()}, got {repr(name)[:40]}") from None


def kind_names() -> tuple[str, ...]:
    """Names of the registered kinds, in registration order (built-ins first)."""
    return tuple(_REGISTRY)


register(BinaryKind("orb", 32, lambda n: cv2.ORB_create(nfeatures=n), upright=True))
register(FloatKind("sift", 128, lambda n: cv2.SIFT_create(nfeatures=n), options=("rootsift",), window_scale=5.3))
BUILTIN_KINDS = ("orb", "sift")
