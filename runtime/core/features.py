"""Local feature extraction (ORB, SIFT, RootSIFT) and the descriptor-vector contract.

Every quantiser consumes *descriptor vectors*: float32 arrays of shape (N, D) where
ORB's 32 bytes are unpacked to D = 256 bits in {0, 1} and SIFT gives D = 128 floats
(L2-normalised, or RootSIFT: L1-normalised then square-rooted, so L2 norm 1).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import cv2
import numpy as np

from aefabmap.errors import ConfigError, InputError

FEATURE_KINDS = ("orb", "sift")



@dataclass(frozen=True)
class FeatureConfig:
    """Settings of the local feature extractor.

    kind: "orb" (binary, 256 bits) or "sift" (float, 128-D).
    max_features: keypoints kept per image (strongest first).
    long_side: the image is resized so that its longer side has this many pixels
        (up or down) before detection, so that datasets of different resolutions
        share one scale; None keeps the native size.
    rootsift: SIFT only: Hellinger-kernel RootSIFT descriptors.
    bucket_grid: 0 keeps the `max_features` strongest keypoints; N > 0 spreads them over an
        N x N grid of the image: the detector proposes `bucket_oversample` x max_features and
        the cells take turns (strongest remaining keypoint of each cell first), so one
        texture-rich region (foliage, a railing) cannot take the whole budget and geometry
        sees points all over the image.
    bucket_oversample: candidates detected per kept keypoint when bucketing.
    clahe: equalise contrast locally (CLAHE, 8x8 tiles, clip 2) before detection.
    """

    kind: str = "orb"
    max_features: int = 500
    long_side: int | None = 640
    rootsift: bool = False
    bucket_grid: int = 0
    bucket_oversample: int = 4
    clahe: bool = False

    def __post_init__(self) -> None:
        if self.kind not in FEATURE_KINDS:
            raise ConfigError(f"feature kind must be one of {FEATURE_KINDS}, got {self.kind!r}")
        if not isinstance(self.max_features, int) or self.max_features < 1:
            raise ConfigError(f"max_features must be a positive integer, got {self.max_features!r}")
        if self.long_side is not None and (not isinstance(self.long_side, int) or self.long_side < 32):
            raise ConfigError(f"long_side must be None or an integer >= 32, got {self.long_side!r}")
        if not isinstance(self.bucket_grid, int) or not (0 <= self.bucket_grid <= 64):
            raise ConfigError(f"bucket_grid must be an integer in [0, 64], got {self.bucket_grid!r}")
        if not isinstance(self.bucket_oversample, int) or not (1 <= self.bucket_oversample <= 16):
            raise ConfigError(f"bucket_oversample must be an integer in [1, 16], got {self.bucket_oversample!r}")
        if self.rootsift and self.kind != "sift":
            raise ConfigError("rootsift applies to SIFT features only")

    @property
    def descriptor_length(self) -> int:
        """Length D of the descriptor vectors the quantiser sees."""
        return 256 if self.kind == "orb" else 128

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> FeatureConfig:
        known = {k: data[k] for k in ("kind", "max_features", "long_side", "rootsift", "bucket_grid",
                                      "bucket_oversample", "clahe") if k in data}
        # A bundle written before bucketing existed was trained without it: keep it that way.
        known.setdefault("bucket_grid", 0)
        known.setdefault("clahe", False)
        return cls(**known)


@dataclass
class Features:
    """Keypoints and descriptors of one image.

    keypoints: (N, 2) float32, x, y in pixels of the ORIGINAL image.
    sizes: (N,) float32 keypoint diameters in original pixels.
    angles: (N,) float32 orientations in degrees (-1 when undefined).
    descriptors: raw descriptors, (N, 32) uint8 for ORB, (N, 128) float32 for SIFT.
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
    """Deterministic ORB/SIFT extractor for one FeatureConfig (not thread-safe)."""

    def __init__(self, config: FeatureConfig | None = None) -> None:
        self.config = config or FeatureConfig()
        c = self.config
        proposed = c.max_features * (c.bucket_oversample if c.bucket_grid else 1)
        if c.kind == "orb":
            self._detector = cv2.ORB_create(nfeatures=proposed)
        else:
            self._detector = cv2.SIFT_create(nfeatures=proposed)
        self._clahe = cv2.createCLAHE(clipLimit=2.0, tileGridSize=(8, 8)) if c.clahe else None

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
        if self._clahe is not None:
            work = self._clahe.apply(work)
        kps, desc = self._detector.detectAndCompute(work, None)
        return self._pack(kps, desc, scale, gray.shape, work.shape)

    def _pack(self, kps, desc, scale: float, shape, work_shape) -> Features:
        c = self.config
        n = 0 if desc is None else len(kps)
        if n == 0:
            width = 32 if c.kind == "orb" else 128
            dtype = np.uint8 if c.kind == "orb" else np.float32
            return Features(
                np.zeros((0, 2), np.float32),
                np.zeros(0, np.float32),
                np.zeros(0, np.float32),
                np.zeros((0, width), dtype),
                (int(shape[0]), int(shape[1])),
            )
        # Strongest first, ties broken by position: a fixed order for fixed input.
        resp = np.array([k.response for k in kps], np.float32)
        pts = np.array([k.pt for k in kps], np.float32)
        order = np.lexsort((pts[:, 0], pts[:, 1], -resp))
        if c.bucket_grid:
            order = order[_bucket_turns(pts[order], work_shape, c.bucket_grid)]
        order = order[: c.max_features]
        pts = pts[order] / scale
        sizes = np.array([kps[i].size for i in order], np.float32) / scale
        angles = np.array([kps[i].angle for i in order], np.float32)
        desc = desc[order]
        if c.kind == "sift":
            desc = desc.astype(np.float32)
            if c.rootsift:
                desc = np.sqrt(desc / np.maximum(desc.sum(axis=1, keepdims=True), 1e-12))
            else:
                desc = desc / np.maximum(np.linalg.norm(desc, axis=1, keepdims=True), 1e-12)
        return Features(pts, sizes, angles, np.ascontiguousarray(desc), (int(shape[0]), int(shape[1])))


def _bucket_turns(pts: np.ndarray, shape_hw: tuple[int, int], grid: int) -> np.ndarray:
    """Order of keypoints pts (K, 2), given strongest first, in which grid cells take turns.

    Returns a permutation of range(K): the strongest keypoint of every cell, then the second
    strongest of every cell, and so on (within a turn, strongest first).
    """
    h, w = shape_hw
    cx = np.minimum((pts[:, 0] * grid / max(w, 1)).astype(np.int64), grid - 1)
    cy = np.minimum((pts[:, 1] * grid / max(h, 1)).astype(np.int64), grid - 1)
    cell = np.maximum(cy, 0) * grid + np.maximum(cx, 0)
    # Rank of each keypoint within its cell (input order is strongest first).
    by_cell = np.argsort(cell, kind="stable")
    sorted_cells = cell[by_cell]
    start = np.r_[0, np.flatnonzero(np.diff(sorted_cells)) + 1]
    run = np.repeat(start, np.diff(np.r_[start, sorted_cells.size]))
    turn = np.empty(cell.size, np.int64)
    turn[by_cell] = np.arange(cell.size) - run
    return np.lexsort((np.arange(cell.size), turn))


def descriptor_vectors(descriptors: np.ndarray, kind: str) -> np.ndarray:
    """Raw descriptors -> float32 (N, D) vectors: ORB bytes unpacked to bits, SIFT unchanged."""
    if kind == "orb":
        if descriptors.dtype != np.uint8 or descriptors.ndim != 2 or descriptors.shape[1] != 32:
            raise InputError(f"ORB descriptors must be (N, 32) uint8, got {descriptors.shape} {descriptors.dtype}")
        return np.unpackbits(descriptors, axis=1).astype(np.float32)
    if kind == "sift":
        if descriptors.ndim != 2 or descriptors.shape[1] != 128:
            raise InputError(f"SIFT descriptors must be (N, 128), got {descriptors.shape}")
        return np.ascontiguousarray(descriptors, dtype=np.float32)
    raise ConfigError(f"unknown feature kind {kind!r}")
