"""ORB descriptors, oriented and upright, from one blurred pyramid (the compiled kernel).

OpenCV's ORB describes a frame's keypoints in `detectAndCompute`, and the upright copies (orientation
0, for verification's upright retry) need a second `compute`: a second pyramid, a second blur and,
per keypoint, Python KeyPoint objects in and out. Here OpenCV only detects; the pyramid is rebuilt and
blurred once as ORB does it, and both descriptors of every keypoint are read off it by
`orb_describe` (runtime/aefabmap_runtime/core/kernels/kernels.c) with ORB's arithmetic: the same bytes
as OpenCV's, which `OrbDescriber.for_detector` checks on a test image before it is used.

ORB's sampling pattern is not exposed by OpenCV; `probe_pattern` reads it off OpenCV's own
descriptors of step images (module docstring of the function), so nothing of OpenCV is copied and a
build of OpenCV with another pattern is followed, or refused by the check.
"""

from __future__ import annotations

import functools

import cv2
import numpy as np

from aefabmap_runtime.core.kernels import native

#: ORB's blur before description: a 7 x 7 Gaussian of sigma 2, applied as two float32 passes
#: (what OpenCV's ORB computes; its 8-bit fixed-point GaussianBlur rounds some pixels otherwise).
BLUR_SIZE = 7
BLUR_SIGMA = 2.0
#: Pattern pairs of a 32-byte ORB descriptor, and the probe's image size and shift range (px):
#: ORB's 31-px patch keeps every pattern point within 15 px of the centre, so the steps sweep
#: +-(2 x 15 + the blur's reach) around it.
PAIRS = 256
_PROBE_SIZE = 201
_PROBE_SHIFTS = range(-40, 41)


def level_scales(n_levels: int, scale_factor: float) -> np.ndarray:
    """(L,) float32 scale of each pyramid level, as ORB computes it: pow in double of the
    factor, rounded to float32."""
    return np.array([np.float32(float(scale_factor) ** level) for level in range(n_levels)], np.float32)


def pyramid(image: np.ndarray, n_levels: int, scale_factor: float,
            compiled: bool | None = None) -> tuple[list[np.ndarray], np.ndarray]:
    """ORB's pyramid of a grayscale (H, W) uint8 image: level 0 is the image; level l is level
    l - 1 resized (bit-exact bilinear) to the image size over the level's scale, rounded (levels
    that would have no pixel are left out). Returns the levels and (L,) float32 1 / scale.

    compiled: resize every level in one call of the compiled kernels (`native.resize_levels`, the
    same bytes) rather than one OpenCV call per level; None: where the kernels are built and
    reproduce OpenCV's levels on a test image (`compiled_resize_agrees`)."""
    inv = (np.float32(1.0) / level_scales(n_levels, scale_factor)).astype(np.float32)
    h, w = image.shape
    sizes = []
    for level in range(1, n_levels):
        size = (int(np.rint(np.float32(w) * inv[level])), int(np.rint(np.float32(h) * inv[level])))
        if min(size) < 1:
            break
        sizes.append(size)
    if compiled is None:
        compiled = compiled_resize_agrees()
    if compiled and sizes and image.dtype == np.uint8 and image.strides[1] == 1:
        levels = [image] + [np.empty((rows, cols), np.uint8) for cols, rows in sizes]
        native.resize_levels(levels)
    else:
        levels = [image]
        for size in sizes:
            levels.append(cv2.resize(levels[-1], size, interpolation=cv2.INTER_LINEAR_EXACT))
    return levels, inv[: len(levels)]


@functools.cache
def compiled_resize_agrees() -> bool:
    """Whether the compiled pyramid (`native.resize_levels`) gives OpenCV's levels here, on a
    seeded test image at ORB's default and an uneven scale; False without the compiled kernels."""
    if not native.available():
        return False
    rng = np.random.default_rng(0)
    image = cv2.resize(rng.integers(0, 256, (61, 83), dtype=np.uint8), (517, 389), interpolation=cv2.INTER_LINEAR)
    for n_levels, factor in ((8, 1.2), (5, 1.37)):
        mine, _ = pyramid(image, n_levels, factor, compiled=True)
        theirs, _ = pyramid(image, n_levels, factor, compiled=False)
        if any(not np.array_equal(a, b) for a, b in zip(mine, theirs)):
            return False
    return True


def blurred(levels: list[np.ndarray]) -> list[np.ndarray]:
    """Each pyramid level blurred as ORB blurs it before description."""
    kernel = cv2.getGaussianKernel(BLUR_SIZE, BLUR_SIGMA, ktype=cv2.CV_32F).ravel()
    return [cv2.sepFilter2D(level, -1, kernel, kernel, borderType=cv2.BORDER_REFLECT_101) for level in levels]


def probe_pattern(orb) -> np.ndarray | None:
    """ORB's (PAIRS, 4) int32 test pattern (x1, y1, x2, y2 around the centre, bit order), read
    off OpenCV's upright descriptors of step images; None when the reading is not consistent.

    A bit is 1 when the blurred value at its first point is below the one at its second. For an
    image that is 0 left of column c and 255 from it, the blurred value depends on x alone and
    rises strictly over the blur's reach, so the bit is 1 for exactly the steps c in
    [x1 - 2, x2 + 3] when x1 < x2 (the falling step gives x1 > x2); rows and diagonals (x + y)
    likewise give y and x + y, which settle pairs with equal x.
    """
    centre = _PROBE_SIZE // 2
    yy, xx = np.mgrid[0:_PROBE_SIZE, 0:_PROBE_SIZE]
    keypoint = [cv2.KeyPoint(float(centre), float(centre), 31.0, 0.0, 1.0, 0, 0)]
    shifts = np.array(list(_PROBE_SHIFTS))

    def bits(image: np.ndarray) -> np.ndarray | None:
        got, desc = orb.compute(image, keypoint)
        if desc is None or len(got) != 1 or desc.shape[1] * 8 != PAIRS:
            return None
        return np.unpackbits(desc[0], bitorder="little")

    def read(coord: np.ndarray, low: int, high: int) -> tuple[np.ndarray, np.ndarray] | None:
        first, second = np.full(PAIRS, np.nan), np.full(PAIRS, np.nan)
        for rising in (True, False):
            lit = []
            for s in shifts:
                step = coord >= centre + s if rising else coord < centre + s
                b = bits(np.where(step, 255, 0).astype(np.uint8))
                if b is None:
                    return None
                lit.append(b)
            lit = np.array(lit, bool)
            on = lit.any(axis=0)
            lo = np.where(on, shifts[np.argmax(lit, axis=0)], 0)
            hi = np.where(on, shifts[len(shifts) - 1 - np.argmax(lit[::-1], axis=0)], 0)
            small, large = lo + low, hi - high
            if rising:
                first[on], second[on] = small[on], large[on]
            else:
                first[on], second[on] = large[on], small[on]
        return first, second

    x = read(xx, 2, 3)
    y = read(yy, 2, 3)
    s = read(xx + yy - centre, 5, 6)  # x + y: the separable blur reaches 3 + 3 along it
    if x is None or y is None or s is None:
        return None
    cols = []  # x1, y1, x2, y2: a coordinate the x or y steps could not settle comes from x + y
    for xi, yi, si in zip(x, y, s):
        xi = np.where(np.isnan(xi), si - yi, xi)
        cols += [xi, np.where(np.isnan(yi), si - xi, yi)]
    points = np.stack(cols, axis=1)
    if np.isnan(points).any() or np.abs(points).max() > 15:
        return None
    return points.astype(np.int32)


class OrbDescriber:
    """Oriented and upright ORB descriptors of keypoints detected by one cv2.ORB (see module doc)."""

    def __init__(self, n_levels: int, scale_factor: float, pattern: np.ndarray) -> None:
        self.n_levels = n_levels
        self.scale_factor = scale_factor
        self.pattern = np.ascontiguousarray(pattern, np.int32)

    @classmethod
    def for_detector(cls, orb) -> OrbDescriber | None:
        """A describer giving `orb`'s own descriptors, or None when it cannot here: no compiled
        kernels, settings it does not cover (patch 31, two-point tests, first level 0), or a
        pattern or pyramid that does not reproduce OpenCV's bytes on the test image."""
        if not native.available() or not isinstance(orb, cv2.ORB):
            return None
        if orb.getPatchSize() != 31 or orb.getWTA_K() != 2 or orb.getFirstLevel() != 0 or orb.getEdgeThreshold() < 31:
            return None
        pattern = _checked_pattern(orb.getNLevels(), orb.getScaleFactor())
        return None if pattern is None else cls(orb.getNLevels(), orb.getScaleFactor(), pattern)

    def describe(self, image: np.ndarray, xy: np.ndarray, angle: np.ndarray, octave: np.ndarray,
                 oriented: bool = True, upright: bool = False,
                 built: tuple[list[np.ndarray], np.ndarray] | None = None,
                 ) -> tuple[np.ndarray | None, np.ndarray | None] | None:
        """Descriptors (N, 32) uint8 of keypoints xy (N, 2) float32 on `image` (level-0 pixels),
        angle (N,) degrees and octave (N,) as ORB detected them; None when a keypoint is out of
        the pyramid's reach (the caller describes with OpenCV instead). built: `pyramid(image)`'s
        result when the caller built it already."""
        n = xy.shape[0]
        if octave.size and (octave.min() < 0 or octave.max() >= self.n_levels):
            return None
        levels, inv = built if built is not None else pyramid(image, self.n_levels, self.scale_factor)
        levels = blurred(levels)
        if octave.size and octave.max() >= len(levels):
            return None
        out_o = np.empty((n, PAIRS // 8), np.uint8) if oriented else None
        out_u = np.empty((n, PAIRS // 8), np.uint8) if upright else None
        outside = native.orb_describe(levels, inv, np.ascontiguousarray(xy[:, 0], np.float32),
                                      np.ascontiguousarray(xy[:, 1], np.float32),
                                      np.ascontiguousarray(angle, np.float32), np.ascontiguousarray(octave, np.int32),
                                      self.pattern, out_o, out_u)
        return None if outside else (out_o, out_u)

    def agrees_with(self, orb) -> bool:
        """Whether this describer gives OpenCV's bytes, oriented and upright, for `orb`'s
        keypoints on a seeded textured test image."""
        rng = np.random.default_rng(0)
        image = cv2.resize(rng.integers(0, 256, (96, 128), dtype=np.uint8), (512, 384), interpolation=cv2.INTER_LINEAR)
        kps = orb.detect(image, None)
        if len(kps) < 50:
            return False
        xy = cv2.KeyPoint_convert(kps).reshape(-1, 2).astype(np.float32)
        angle = np.array([k.angle for k in kps], np.float32)
        octave = np.array([k.octave for k in kps], np.int32)
        mine = self.describe(image, xy, angle, octave, oriented=True, upright=True)
        if mine is None:
            return False
        got, ref = orb.compute(image, kps)
        flat = [cv2.KeyPoint(k.pt[0], k.pt[1], k.size, 0.0, k.response, k.octave, 0) for k in kps]
        got_u, ref_u = orb.compute(image, flat)
        return (ref is not None and ref_u is not None and len(got) == len(kps) == len(got_u)
                and np.array_equal(mine[0], ref) and np.array_equal(mine[1], ref_u))


@functools.lru_cache(maxsize=4)
def _checked_pattern(n_levels: int, scale_factor: float) -> np.ndarray | None:
    """The probed pattern, once it reproduced OpenCV's bytes with this pyramid (None: not), once
    per process and pyramid setting (every thread's extractor asks)."""
    orb = cv2.ORB_create(scaleFactor=scale_factor, nlevels=n_levels)
    pattern = probe_pattern(orb)
    if pattern is None or not OrbDescriber(n_levels, scale_factor, pattern).agrees_with(orb):
        return None
    pattern.setflags(write=False)
    return pattern
