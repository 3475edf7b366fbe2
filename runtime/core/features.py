"""Local feature extraction (ORB, SIFT, RootSIFT, any registered kind) and the descriptor-vector contract.

Every quantiser consumes *descriptor vectors*: float32 arrays of shape (N, D) where
ORB's 32 bytes are unpacked to D = 256 bits in {0, 1} and SIFT gives D = 128 floats
(L2-normalised, or RootSIFT: L1-normalised then square-rooted, so L2 norm 1). What each kind
is (widths, dtype, distance, vector form, extractor) is declared in feature_kinds.py.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import cv2
import numpy as np

from aefabmap.errors import ConfigError, InputError
from aefabmap.runtime.core.feature_kinds import FeatureKind, get_kind


@dataclass(frozen=True)
class FeatureConfig:
    """Settings of the local feature extractor.

    kind: a registered feature kind (feature_kinds.py): "orb" (binary, 256 bits) or
        "sift" (float, 128-D) built in.
    max_features: keypoints kept per image (strongest first).
    long_side: the image is resized so that its longer side has this many pixels
        (up or down) before detection, so that datasets of different resolutions
        share one scale; None keeps the native size.
    rootsift: SIFT only: Hellinger-kernel RootSIFT descriptors.
    """

    kind: str = "orb"
    max_features: int = 500
    long_side: int | None = 640
    rootsift: bool = False

    def __post_init__(self) -> None:
        spec = get_kind(self.kind)
        if not isinstance(self.max_features, int) or self.max_features < 1:
            raise ConfigError(f"max_features must be a positive integer, got {self.max_features!r}")
        if self.long_side is not None and (not isinstance(self.long_side, int) or self.long_side < 32):
            raise ConfigError(f"long_side must be None or an integer >= 32, got {self.long_side!r}")
        if self.rootsift and "rootsift" not in spec.options:
            raise ConfigError(f"rootsift applies to SIFT features only, not to {self.kind!r}")

    @property
    def spec(self) -> FeatureKind:
        """The registered FeatureKind of `kind`."""
        return get_kind(self.kind)

    @property
    def descriptor_length(self) -> int:
        """Length D of the descriptor vectors the quantiser sees."""
        return self.spec.vector_length

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> "FeatureConfig":
        known = {k: data[k] for k in ("kind", "max_features", "long_side", "rootsift") if k in data}
        return cls(**known)


@dataclass
class Features:
    """Keypoints and descriptors of one image.

    keypoints: (N, 2) float32, x, y in pixels of the ORIGINAL image.
    sizes: (N,) float32 keypoint diameters in original pixels.
    angles: (N,) float32 orientations in degrees (-1 when undefined).
    descriptors: raw descriptors (N, width) of the kind's dtype: (N, 32) uint8 for ORB,
        (N, 128) float32 for SIFT.
    image_shape: (height, width) of the original image.
    """

    keypoints: np.ndarray
    sizes: np.ndarray
    angles: np.ndarray
    descriptors: np.ndarray
    image_shape: tuple[int, int]

    def __len__(self) -> int:
        return int(self.keypoints.shape[0])


def to_gray(image: np.ndarray) -> np.ndarray:
    """Convert an (H, W) or (H, W, 3|4) uint8 BGR(A) array to grayscale (H, W)."""
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8:
        raise InputError("image must be a uint8 numpy array")
    if image.ndim == 2:
        return image
    if image.ndim == 3 and image.shape[2] == 1:
        return image[:, :, 0]
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.ndim == 3 and image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY)
    raise InputError(f"unsupported image shape {image.shape}")


class FeatureExtractor:
    """Deterministic extractor (the kind's OpenCV detector) for one FeatureConfig (not thread-safe)."""

    def __init__(self, config: FeatureConfig | None = None) -> None:
        self.config = config or FeatureConfig()
        self.kind = self.config.spec
        self._detector = self.kind.create(self.config.max_features)

    def extract(self, image: np.ndarray) -> Features:
        """Extract features from a grayscale (H, W) or BGR(A) (H, W, 3|4) uint8 array."""
        gray = to_gray(image)
        if gray.shape[0] < 8 or gray.shape[1] < 8:
            raise InputError(f"image of {gray.shape[1]}x{gray.shape[0]} pixels is too small")
        scale = 1.0
        work = gray
        if self.config.long_side is not None:
            scale = self.config.long_side / max(gray.shape)
            if abs(scale - 1.0) > 1e-6:
                interp = cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR
                size = (max(1, round(gray.shape[1] * scale)), max(1, round(gray.shape[0] * scale)))
                work = cv2.resize(gray, size, interpolation=interp)
                scale = size[0] / gray.shape[1]
        kps, desc = self._detector.detectAndCompute(work, None)
        return self._pack(kps, desc, scale, gray.shape)

    def _pack(self, kps, desc, scale: float, shape) -> Features:
        c = self.config
        n = 0 if desc is None else len(kps)
        if n == 0:
            return Features(
                np.zeros((0, 2), np.float32),
                np.zeros(0, np.float32),
                np.zeros(0, np.float32),
                self.kind.empty(),
                (int(shape[0]), int(shape[1])),
            )
        # Strongest first, ties broken by position: a fixed order for fixed input.
        resp = np.array([k.response for k in kps], np.float32)
        pts = np.array([k.pt for k in kps], np.float32)
        order = np.lexsort((pts[:, 0], pts[:, 1], -resp))[: c.max_features]
        pts = pts[order] / scale
        sizes = np.array([kps[i].size for i in order], np.float32) / scale
        angles = np.array([kps[i].angle for i in order], np.float32)
        desc = self.kind.finish(desc[order], c.rootsift)
        return Features(pts, sizes, angles, desc, (int(shape[0]), int(shape[1])))


def descriptor_vectors(descriptors: np.ndarray, kind: str) -> np.ndarray:
    """Raw descriptors -> float32 (N, D) vectors in the kind's declared form (ORB: bits)."""
    return get_kind(kind).vectors(descriptors)
