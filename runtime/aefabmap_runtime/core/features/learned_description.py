"""A learned binary descriptor for ORB's keypoints (pure: no I/O).

ORB's BRIEF compares 256 fixed pairs of pixels in the keypoint's 31-px window. The learned
descriptor reads the same window, turned by the keypoint's angle, as a PATCH x PATCH grid at STEP-px
steps of the blurred pyramid level the keypoint was found on (the blur ORB describes from), and keeps
the signs of BITS learned projections of the patch minus its mean. The result is 256 bits matched by
Hamming distance like ORB's, so words, verification and the keypoint store work on it unchanged.

The arithmetic is defined here, integer wherever it can be, and the compiled kernel
(`native.learned_describe`) and the numpy form below compute the same bytes: a sample's position
in float32 (c u - s v + cx, s u + c v + cy, in that order), rounded to 1/32 px (to nearest, ties to
even); its value the bilinear mix of four pixels in 1/32 steps, rounded, indices clamped to the
level (its edge repeats); bit b set when SAMPLES * (w_b . patch) > sum(patch) * sum(w_b), exactly
sum_i w_bi (p_i - mean(p)) > 0, in integers (int8 weights, trainer/aefabmap_trainer/learned_descriptor.py).
A board and a workstation give the same bits for the same turns (c, s come from numpy's float32
cos and sin). Why a projection and not a deeper network: its cost is one (N, 256) x (256, 256)
product per frame (docs/results.md, "A learned descriptor").
"""

from __future__ import annotations

import numpy as np

from aefabmap_runtime.core.features.orb_description import blurred, pyramid
from aefabmap_runtime.core.kernels import native
from aefabmap_runtime.errors import InputError

#: Samples per side of the patch, their spacing in level pixels, and the bits of a descriptor.
#: 16 samples 2 px apart span ORB's 31-px window (offsets -15 .. +15).
PATCH = 16
STEP = 2.0
BITS = 256
SAMPLES = PATCH * PATCH

_OFFSETS = (np.arange(PATCH, dtype=np.float32) - (PATCH - 1) / 2.0) * np.float32(STEP)
_GRID_U, _GRID_V = (np.ascontiguousarray(g.reshape(-1)) for g in np.meshgrid(_OFFSETS, _OFFSETS))  # (SAMPLES,)
_TO_RADIANS = np.float32(np.pi / 180.0)


def turns(angle: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(cos, sin) (N,) float32 of angles (N,) in degrees."""
    rad = np.asarray(angle, np.float32) * _TO_RADIANS
    return np.cos(rad), np.sin(rad)


def _checked_octaves(octave: np.ndarray, n_levels: int) -> np.ndarray:
    """octave (N,) as C-contiguous int32; InputError for one outside [0, n_levels)."""
    octave = np.asarray(octave)
    if octave.size and (octave.min() < 0 or octave.max() >= n_levels):
        raise InputError(f"keypoint octaves must lie in [0, {n_levels}), got {octave.min()}..{octave.max()}")
    return np.ascontiguousarray(octave, np.int32)


def sample_patches(levels: list[np.ndarray], inv: np.ndarray, xy: np.ndarray, angle: np.ndarray,
                   octave: np.ndarray) -> np.ndarray:
    """(N, SAMPLES) uint8 patches (module docstring) of keypoints xy (N, 2) (level-0 pixels), angle
    (N,) degrees and octave (N,) on the blurred pyramid `levels` with (L,) `inv` = 1 / level scale."""
    n = xy.shape[0]
    out = np.zeros((n, SAMPLES), np.uint8)
    if n == 0:
        return out
    octave = _checked_octaves(octave, len(levels)).astype(np.int64)
    cos, sin = (t[:, None] for t in turns(angle))
    for level in np.unique(octave).tolist():
        rows = np.nonzero(octave == level)[0]
        image = levels[level]
        cx = (np.asarray(xy[rows, 0], np.float32) * np.float32(inv[level]))[:, None]
        cy = (np.asarray(xy[rows, 1], np.float32) * np.float32(inv[level]))[:, None]
        px = (cos[rows] * _GRID_U - sin[rows] * _GRID_V) + cx
        py = (sin[rows] * _GRID_U + cos[rows] * _GRID_V) + cy
        fx_all = np.rint(px * np.float32(32)).astype(np.int32)
        fy_all = np.rint(py * np.float32(32)).astype(np.int32)
        ix, iy, fx, fy = fx_all >> 5, fy_all >> 5, fx_all & 31, fy_all & 31
        x0, x1 = np.clip(ix, 0, image.shape[1] - 1), np.clip(ix + 1, 0, image.shape[1] - 1)
        y0, y1 = np.clip(iy, 0, image.shape[0] - 1), np.clip(iy + 1, 0, image.shape[0] - 1)
        p00, p01 = image[y0, x0].astype(np.int32), image[y0, x1].astype(np.int32)
        p10, p11 = image[y1, x0].astype(np.int32), image[y1, x1].astype(np.int32)
        gx, gy = 32 - fx, 32 - fy
        out[rows] = (gx * gy * p00 + fx * gy * p01 + gx * fy * p10 + fx * fy * p11 + 512) >> 10
    return out


class LearnedDescription:
    """The learned projection: int8 weights (BITS, SAMPLES), one row per bit.

    Bit b of a patch p (SAMPLES grey levels) is set when sum_i W[b, i] * (p_i - mean(p)) > 0."""

    def __init__(self, weights: np.ndarray) -> None:
        w = np.asarray(weights)
        if w.shape != (BITS, SAMPLES) or w.dtype != np.int8:
            raise InputError(f"a learned descriptor needs ({BITS}, {SAMPLES}) int8 weights, got {w.shape} {w.dtype}")
        if not np.any(w):
            raise InputError("a learned descriptor's weights are all zero")
        self.weights = np.array(w, np.int8)
        self.weights.setflags(write=False)
        # float32 copies of integers: exact products (module docstring); row sums over SAMPLES for
        # the mean; for the compiled kernel, int64 sums and the weights in its two layouts: int16
        # pairs (SAMPLES / 2, BITS, 2) and int8 quads (SAMPLES / 4, BITS, 4) (native.learned_describe).
        self._w = np.ascontiguousarray(self.weights.T, np.float32)
        self._row_sums = self.weights.sum(axis=1, dtype=np.int64)
        self._row_means = self._row_sums.astype(np.float64) / SAMPLES
        self._pairs = np.ascontiguousarray(self.weights.astype(np.int16).reshape(BITS, SAMPLES // 2, 2).transpose(1, 0, 2))
        self._quads = np.ascontiguousarray(self.weights.reshape(BITS, SAMPLES // 4, 4).transpose(1, 0, 2))

    def describe(self, levels: list[np.ndarray], inv: np.ndarray, xy: np.ndarray, angle: np.ndarray,
                 octave: np.ndarray, compiled: bool | None = None, form: str = native.LEARNED_FORMS[0]) -> np.ndarray:
        """(N, BITS // 8) uint8 descriptors of keypoints (as `sample_patches`): by the compiled
        kernel where it is built (compiled None), else, or with compiled False, by numpy (the same
        bytes). form: the most specialised compiled form used (native.LEARNED_FORMS; the same bytes)."""
        if compiled is None:
            compiled = native.available()
        if not compiled:
            return self.bits(sample_patches(levels, inv, xy, angle, octave))
        octave = _checked_octaves(octave, len(levels))
        cos, sin = turns(angle)
        out = np.empty((xy.shape[0], BITS // 8), np.uint8)
        native.learned_describe(levels, np.ascontiguousarray(inv, np.float32),
                                np.ascontiguousarray(xy[:, 0], np.float32), np.ascontiguousarray(xy[:, 1], np.float32),
                                np.ascontiguousarray(cos), np.ascontiguousarray(sin), octave, _GRID_U, _GRID_V,
                                self._pairs, self._quads, self._row_sums, out, form)
        return out

    def bits(self, patches: np.ndarray) -> np.ndarray:
        """(N, BITS // 8) uint8 descriptors of (N, SAMPLES) uint8 patches (bit b is bit b % 8 of
        byte b // 8, as numpy's little bit order)."""
        if patches.shape[0] == 0:
            return np.zeros((0, BITS // 8), np.uint8)
        p = np.asarray(patches, np.uint8)
        # sum_i W (p_i - mean) > 0  <=>  W . p > sum(p) * sum(W) / SAMPLES. W . p is a whole number
        # below 2**24 (exact in float32); the right side is exact in float64 (SAMPLES is a power of 2).
        dots = p.astype(np.float32) @ self._w
        sums = p.sum(axis=1, dtype=np.int64).astype(np.float64)
        return np.packbits(dots > np.multiply.outer(sums, self._row_means), axis=1, bitorder="little")


class LearnedDescriber:
    """Oriented and upright learned descriptors from ORB's blurred pyramid: the describer
    FeatureExtractor uses for FeatureConfig(descriptor="learned") (same call as OrbDescriber)."""

    def __init__(self, n_levels: int, scale_factor: float, description: LearnedDescription) -> None:
        self.n_levels = n_levels
        self.scale_factor = scale_factor
        self.description = description

    def describe(self, image: np.ndarray, xy: np.ndarray, angle: np.ndarray, octave: np.ndarray,
                 oriented: bool = True, upright: bool = False,
                 built: tuple[list[np.ndarray], np.ndarray] | None = None,
                 ) -> tuple[np.ndarray | None, np.ndarray | None]:
        """(oriented, upright) (N, 32) uint8 descriptors (None where not asked) of keypoints on
        `image` (see OrbDescriber.describe); built: `pyramid(image)` when already built."""
        levels, inv = built if built is not None else pyramid(image, self.n_levels, self.scale_factor)
        levels = blurred(levels)
        d = self.description
        out_o = d.describe(levels, inv, xy, angle, octave) if oriented else None
        out_u = d.describe(levels, inv, xy, np.zeros_like(angle), octave) if upright else None
        return out_o, out_u
