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

from aefabmap_runtime.errors import ConfigError, InputError
from aefabmap_runtime.core.features.feature_kinds import FeatureKind, get_kind
from aefabmap_runtime.core.features.learned_description import LearnedDescriber, LearnedDescription, sample_patches
from aefabmap_runtime.core.features.orb_description import OrbDescriber, blurred, pyramid
from aefabmap_runtime.core.features.orb_levels import OrbLevelDetector, keypoint_rows

#: Shortest image side (px) the extractor works on, before and after resizing: OpenCV's
#: ORB pyramid shrinks each level by 1.2 and asserts when a level reaches 0 px.
MIN_IMAGE_SIDE = 8
#: Most elongated image (long side / short side) accepted. Principle: at the default 640-px
#: long side, a 10:1 image keeps a 64-px short side, just over ORB's two 31-px borders where
#: no keypoint can be described; anything more elongated yields (almost) no features.
#: Cameras deliver 4:3 to 21:9 (2.3:1), stereo pairs side by side about 3.6:1.
MAX_ASPECT_RATIO = 10


#: Bounds of FeatureConfig (OpenCV takes C ints; a board never wants more): 100 000
#: keypoints is 20x the largest vocabulary-training setting; 8192 px covers 8K sensors.
MAX_FEATURES = 100_000
MIN_LONG_SIDE = 32
MAX_LONG_SIDE = 8192


def _int_in(value, low: int, high: int) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and low <= value <= high


def _clip(value, limit: int = 40) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def image_shape_problem(height: int, width: int, long_side: int | None = None) -> str | None:
    """Why an image of ``height`` x ``width`` px cannot be used, or None when it can.

    Too small (a side under MIN_IMAGE_SIDE), too elongated (over MAX_ASPECT_RATIO), or too
    small once resized to ``long_side`` px (None: no resizing). Pure arithmetic, so callers
    can refuse an image from its header before decoding it.
    """
    short, long_ = min(height, width), max(height, width)
    if short < MIN_IMAGE_SIDE:
        return f"image of {width}x{height} pixels is too small (sides under {MIN_IMAGE_SIDE} px)"
    if long_ > MAX_ASPECT_RATIO * short:
        return f"image of {width}x{height} pixels is too elongated (more than {MAX_ASPECT_RATIO}:1)"
    if long_side is not None and round(short * long_side / long_) < MIN_IMAGE_SIDE:
        return (
            f"image of {width}x{height} pixels resized to a {long_side}-px long side would have a short side "
            f"under {MIN_IMAGE_SIDE} px"
        )
    return None


#: Version of what the extractor does beyond its FeatureConfig (e.g. how it resizes): caches of
#: extracted features are keyed by it, so a change that gives other features for the same
#: settings must bump it. 2: small frames upsampled by the bit-exact bilinear.
EXTRACTION_VERSION = 2

#: FeatureConfig.descriptor values: ORB's own tests, or the bundle's learned projection.
DESCRIPTORS = ("brief", "learned")


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
    bucket_grid: 0 keeps the `max_features` strongest keypoints; N > 0 spreads them over an
        N x N grid of the image: the detector proposes `bucket_oversample` x max_features and
        the cells take turns (strongest remaining keypoint of each cell first), so one
        texture-rich region (foliage, a railing) cannot take the whole budget and geometry
        sees points all over the image.
    bucket_oversample: candidates detected per kept keypoint when bucketing.
    clahe: equalise contrast locally (CLAHE, 8x8 tiles, clip 2) before detection.
    contrast_stretch: before detection, map the image's STRETCH_PERCENTILE-th and
        (100 - STRETCH_PERCENTILE)-th grey-level percentiles to 0 and 255 (one look-up table, gain at
        most MAX_STRETCH_GAIN): FAST's fixed threshold then finds corners in a dark or low-contrast
        frame (night, dusk, fog) where it finds them in a well-exposed one, and a well-exposed frame
        is left almost as it is. Measured on training images (docs/results.md, "Light").
    descriptor: ORB only: "brief" (ORB's own tests) or "learned" (a projection trained with the
        bundle, features/learned_description.py; the extractor needs its LearnedDescription).
    """

    kind: str = "orb"
    max_features: int = 500
    long_side: int | None = 640
    rootsift: bool = False
    bucket_grid: int = 0
    bucket_oversample: int = 4
    clahe: bool = False
    contrast_stretch: bool = False
    descriptor: str = "brief"

    def __post_init__(self) -> None:
        if not isinstance(self.kind, str):
            raise ConfigError(f"feature kind must be a string, got {_clip(self.kind)}")
        spec = get_kind(self.kind)
        if not _int_in(self.max_features, 1, MAX_FEATURES):
            raise ConfigError(f"max_features must be an integer in [1, {MAX_FEATURES}], got {_clip(self.max_features)}")
        if self.long_side is not None and not _int_in(self.long_side, MIN_LONG_SIDE, MAX_LONG_SIDE):
            raise ConfigError(
                f"long_side must be None or an integer in [{MIN_LONG_SIDE}, {MAX_LONG_SIDE}], got {_clip(self.long_side)}"
            )
        if not _int_in(self.bucket_grid, 0, 64):
            raise ConfigError(f"bucket_grid must be an integer in [0, 64], got {_clip(self.bucket_grid)}")
        if not _int_in(self.bucket_oversample, 1, 16):
            raise ConfigError(f"bucket_oversample must be an integer in [1, 16], got {_clip(self.bucket_oversample)}")
        if not isinstance(self.clahe, bool):
            raise ConfigError(f"clahe must be true or false, got {_clip(self.clahe)}")
        if not isinstance(self.contrast_stretch, bool):
            raise ConfigError(f"contrast_stretch must be true or false, got {_clip(self.contrast_stretch)}")
        if not isinstance(self.rootsift, bool):
            raise ConfigError(f"rootsift must be true or false, got {_clip(self.rootsift)}")
        if self.rootsift and "rootsift" not in spec.options:
            raise ConfigError(f"rootsift applies to SIFT features only, not to {self.kind!r}")
        if self.descriptor not in DESCRIPTORS:
            raise ConfigError(f"descriptor must be one of {DESCRIPTORS}, got {_clip(self.descriptor)}")
        if self.descriptor == "learned" and self.kind != "orb":
            raise ConfigError(f"the learned descriptor describes ORB keypoints, not {self.kind!r}")

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
    def from_dict(cls, data: dict) -> FeatureConfig:
        known = {k: data[k] for k in ("kind", "max_features", "long_side", "rootsift", "bucket_grid",
                                      "bucket_oversample", "clahe", "contrast_stretch", "descriptor") if k in data}
        # A bundle written before bucketing existed was trained without it: keep it that way.
        known.setdefault("bucket_grid", 0)
        known.setdefault("clahe", False)
        known.setdefault("contrast_stretch", False)  # bundles written before it existed: none
        return cls(**known)


@dataclass
class Features:
    """Keypoints and descriptors of one image.

    keypoints: (N, 2) float32, x, y in pixels of the ORIGINAL image.
    sizes: (N,) float32 keypoint diameters in original pixels.
    descriptors: raw descriptors (N, width) of the kind's dtype: (N, 32) uint8 for ORB,
        (N, 128) float32 for SIFT.
    image_shape: (height, width) of the original image.
    upright: None, or the descriptors of the same keypoints computed with their orientation set
        to 0 (same shape and dtype as descriptors; `FeatureExtractor(upright=True)`).
    """

    keypoints: np.ndarray
    sizes: np.ndarray
    descriptors: np.ndarray
    image_shape: tuple[int, int]
    upright: np.ndarray | None = None

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
    """Deterministic extractor (the kind's OpenCV detector) for one FeatureConfig (not thread-safe).

    upright: also describe every kept keypoint with its orientation set to 0 (`Features.upright`,
        for verification: VerificationConfig.upright), when the kind can (`FeatureKind.upright`).
        The words come from the oriented descriptors, as in training.
    """

    def __init__(self, config: FeatureConfig | None = None, upright: bool = False,
                 learned: LearnedDescription | None = None) -> None:
        self.config = config or FeatureConfig()
        c = self.config
        self.kind = c.spec
        self.upright = bool(upright) and self.kind.upright
        if (c.descriptor == "learned") != (learned is not None):
            raise ConfigError("descriptor 'learned' needs the bundle's learned projection, and only it takes one")
        self.learned = learned
        # Bucketing proposes more keypoints than it keeps, then spreads the budget over a grid.
        self._detector = self.kind.create(c.max_features * (c.bucket_oversample if c.bucket_grid else 1))
        self._clahe = cv2.createCLAHE(clipLimit=2.0, tileGridSize=(8, 8)) if c.clahe else None
        # ORB: OpenCV detects, the compiled kernel describes both orientations from one blurred
        # pyramid, OpenCV's bytes (features/orb_description.py); None: OpenCV describes. With the
        # describer, the pyramid is built once for both: OpenCV detects on each of its levels
        # (features/orb_levels.py; None: cv2.ORB builds its own).
        if learned is not None:
            # Detected on the pyramid the projection reads (compiled or per-level OpenCV).
            self._levels = OrbLevelDetector.for_detector(self._detector)
            if self._levels is None:
                raise ConfigError("this OpenCV's ORB cannot detect by pyramid level: no learned descriptor here")
            self._describer = LearnedDescriber(self._levels.n_levels, self._levels.scale_factor, learned)
        else:
            self._describer = OrbDescriber.for_detector(self._detector)
            self._levels = OrbLevelDetector.for_detector(self._detector) if self._describer is not None else None

    def replace_detector(self, detector) -> None:
        """Detect (and describe) with another OpenCV Feature2D from now on (benchmarks of other
        front-ends): the compiled ORB describer and level detector belong to this extractor's own
        cv2.ORB, so they are dropped with it."""
        if self.learned is not None:
            raise ConfigError("a learned-descriptor extractor keeps its own ORB detector")
        self._detector, self._describer, self._levels = detector, None, None

    def extract(self, image: np.ndarray) -> Features:
        """Extract features from a grayscale (H, W) or BGR(A) (H, W, 3|4) uint8 array.

        Raises InputError for anything else, and for shapes it cannot use
        (see :func:`image_shape_problem`), before any OpenCV call.
        """
        gray, scale, work = self._work_image(image)
        if self._describer is not None:
            if self._levels is not None:
                built = pyramid(work, self._levels.n_levels, self._levels.scale_factor)
                xy, attrs = self._levels.detect(built[0])
            else:
                built, (xy, attrs) = None, keypoint_rows(self._detector.detect(work, None))
            packed = self._pack_described(xy, attrs, scale, gray.shape, work, built)
            if packed is not None:
                return packed
        kps, desc = self._detector.detectAndCompute(work, None)
        return self._pack(kps, desc, scale, gray.shape, work)

    def keypoint_patches(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The kept ORB keypoints of an image as the learned descriptor reads them (its training):
        keypoints (N, 2) float32 in the image's pixels, octave (N,) int32 and (N, SAMPLES) uint8
        patches (features/learned_description.py). Raises InputError as `extract` does, and
        ConfigError for a kind other than ORB or an OpenCV that cannot detect by level."""
        levels_detector = self._levels or (OrbLevelDetector.for_detector(self._detector) if self.kind.name == "orb" else None)
        if levels_detector is None:
            raise ConfigError("keypoint patches need ORB detected by pyramid level")
        gray, scale, work = self._work_image(image)
        levels, inv = pyramid(work, levels_detector.n_levels, levels_detector.scale_factor)
        xy, attrs = levels_detector.detect(levels)
        order = self._kept(xy, attrs[:, 0], work.shape)
        xy, attrs = xy[order], attrs[order]
        octave = attrs[:, 3].astype(np.int32)
        return xy / scale, octave, sample_patches(blurred(levels), inv, xy, attrs[:, 2], octave)

    def _work_image(self, image: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
        """(gray, scale, work): the grey image, and the detection image `work` (resized by `scale`,
        contrast stretched or equalised as configured). Raises InputError (see `extract`)."""
        if not isinstance(image, np.ndarray) or image.ndim not in (2, 3):
            raise InputError(f"image must be an (H, W) or (H, W, C) array, got {getattr(image, 'shape', type(image))}")
        problem = image_shape_problem(image.shape[0], image.shape[1], self.config.long_side)
        if problem is not None:
            raise InputError(problem)
        gray = to_gray(image)
        work, scale = detection_scale(gray, self.config.long_side)
        if self.config.contrast_stretch:
            work = stretch_contrast(work)
        if self._clahe is not None:
            work = self._clahe.apply(work)
        return gray, scale, work

    def _kept(self, pts: np.ndarray, response: np.ndarray, shape_hw: tuple[int, int]) -> np.ndarray:
        """Indices of the keypoints kept (pts (N, 2) on the detection image, response (N,)), in
        their order: strongest first, ties broken by position (a fixed order for fixed input),
        spread over the grid when bucketing, at most max_features."""
        c = self.config
        order = np.lexsort((pts[:, 0], pts[:, 1], -response))
        if c.bucket_grid:
            order = order[_bucket_turns(pts[order], shape_hw, c.bucket_grid)]
        return order[: c.max_features]

    def _pack_described(self, pts: np.ndarray, attrs: np.ndarray, scale: float, shape, work: np.ndarray,
                        built: tuple[list[np.ndarray], np.ndarray] | None) -> Features | None:
        """As `_pack`, for keypoints pts (N, 2) with (N, 4) rows (response, size, angle, octave)
        (`orb_levels.keypoint_rows`), the kept ones described by the compiled kernel (None: it
        cannot describe one of them; the caller lets OpenCV describe the frame). built: `work`'s
        `pyramid` when already built."""
        c = self.config
        if len(pts) == 0:
            return self._pack([], None, scale, shape, work)
        order = self._kept(pts, attrs[:, 0], work.shape)
        kept = attrs[order]
        described = self._describer.describe(work, pts[order], kept[:, 2], kept[:, 3].astype(np.int32),
                                             oriented=True, upright=self.upright, built=built)
        if described is None:
            return None
        desc, upright = described
        return Features(pts[order] / scale, kept[:, 1] / scale, self.kind.finish(desc, c.rootsift),
                        (int(shape[0]), int(shape[1])),
                        self.kind.finish(upright, c.rootsift) if upright is not None else None)

    def _pack(self, kps, desc, scale: float, shape, work: np.ndarray) -> Features:
        c = self.config
        n = 0 if desc is None else len(kps)
        if n == 0:
            return Features(
                np.zeros((0, 2), np.float32),
                np.zeros(0, np.float32),
                self.kind.empty(),
                (int(shape[0]), int(shape[1])),
            )
        # Strongest first, ties broken by position: a fixed order for fixed input. (KeyPoint_convert
        # and fromiter read the attributes at C speed where a list per attribute costs far more;
        # each fromiter still has a cost, so only the attributes used are read: docs/results.md,
        # "Per frame".)
        pts = cv2.KeyPoint_convert(kps).reshape(-1, 2).astype(np.float32, copy=False)
        order = self._kept(pts, np.fromiter((k.response for k in kps), np.float32, n), work.shape)
        pts = pts[order] / scale
        sizes = np.fromiter((k.size for k in kps), np.float32, n)[order] / scale
        upright = self.kind.finish(self._upright(work, kps, order, desc), c.rootsift) if self.upright else None
        desc = self.kind.finish(desc[order], c.rootsift)
        return Features(pts, sizes, desc, (int(shape[0]), int(shape[1])), upright)

    def _upright(self, work: np.ndarray, kps, order: np.ndarray, desc: np.ndarray) -> np.ndarray:
        """Raw descriptors of kps[order], in that order, computed with orientation 0 on the
        detection image `work`. A keypoint the describer drops keeps its oriented descriptor."""
        chosen = []
        for j, i in enumerate(order.tolist()):
            k = kps[i]
            k.angle, k.class_id = 0.0, j  # class_id: the row, whatever order compute() returns
            chosen.append(k)
        got, raw = self._detector.compute(work, chosen)
        out = desc[order].copy()
        if raw is not None and len(got):
            rows = np.fromiter((k.class_id for k in got), np.int64, len(got))
            ok = (rows >= 0) & (rows < out.shape[0])
            out[rows[ok]] = raw[ok]
        return out


#: contrast_stretch: the percentile (each end) mapped to black / white, and the largest gain (a
#: nearly uniform frame, a lens cap or fog, is not blown up into noise).
STRETCH_PERCENTILE = 1.0
MAX_STRETCH_GAIN = 8.0


def detection_scale(gray: np.ndarray, long_side: int | None) -> tuple[np.ndarray, float]:
    """(work, scale): gray (H, W) uint8 resized so that its long side is `long_side` px (None:
    as it is), and the factor applied to x (1.0 when unchanged)."""
    if long_side is None:
        return gray, 1.0
    scale = long_side / max(gray.shape)
    if abs(scale - 1.0) <= 1e-6:
        return gray, 1.0
    # Upsampling by OpenCV's bit-exact bilinear: its plain INTER_LINEAR rounds differently on x86
    # and ARM, so a board would detect other keypoints than the machine its settings were
    # measured on (docs/results.md, "The board's arithmetic").
    interp = cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR_EXACT
    size = (max(1, round(gray.shape[1] * scale)), max(1, round(gray.shape[0] * scale)))
    return cv2.resize(gray, size, interpolation=interp), size[0] / gray.shape[1]


def stretch_contrast(gray: np.ndarray) -> np.ndarray:
    """gray (H, W) uint8 with its grey levels stretched linearly (see FeatureConfig.contrast_stretch)."""
    hist = cv2.calcHist([gray], [0], None, [256], [0, 256]).ravel()
    cdf = np.cumsum(hist)
    lo = int(np.searchsorted(cdf, cdf[-1] * STRETCH_PERCENTILE / 100.0))
    hi = int(np.searchsorted(cdf, cdf[-1] * (1.0 - STRETCH_PERCENTILE / 100.0)))
    gain = 255.0 / max(hi - lo, 255.0 / MAX_STRETCH_GAIN)
    lut = np.clip(np.rint((np.arange(256) - lo) * gain), 0, 255).astype(np.uint8)
    return cv2.LUT(gray, lut)


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
    """Raw descriptors -> float32 (N, D) vectors in the kind's declared form (ORB: bits)."""
    return get_kind(kind).vectors(descriptors)
