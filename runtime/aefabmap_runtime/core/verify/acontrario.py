"""A-contrario significance of a two-view model: the number of false alarms (pure numpy).

Background model (Moisan & Stival's ORSA / AC-RANSAC): the n tentative matches are
independent points spread uniformly over the image. Under it, the chance that one match lies
within eps of what a model predicts is

    alpha(eps) = (2 eps D) / A      for a point-to-line error (F, E: a band around the line),
    alpha(eps) = (pi eps^2) / A     for a point-to-point error (H: a disc around the point;
                                    P: a 3-D point's reprojection under a camera pose),

with D the diagonal and A the area of the region the points fall in. A model computed from a
minimal sample of s matches (F: 7, up to 3 solutions; E: 5, up to 10; H: 4, one; P, a pose
from 3-D points seen in an image: 5, one, as OpenCV's EPnP RANSAC draws them) that has k of
the n matches within eps_k (the k-th smallest error) is expected to happen by chance

    NFA(k) = n_out * (n - s) * C(n, k) * C(k, s) * alpha(eps_k) ** (k - s)

times: (n - s) values of k are tried, C(n, k) subsets could be the inliers, C(k, s) of their
subsets could be the sample that made the model, and the k - s other inliers each fell in
their band by chance. The model is meaningful when min over k of NFA(k) is small: NFA < 1
means fewer than one such coincidence is expected in the whole search. Everything here is in
log10 so that NFA of 1e-40 and 1e+40 are both representable.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# Minimal sample size and the number of models one sample can give.
SAMPLE_SIZE = {"F": 7, "E": 5, "H": 4, "P": 5}
MODELS_PER_SAMPLE = {"F": 3, "E": 10, "H": 1, "P": 1}
# Exponent of eps in alpha: 1 for a band around a line, 2 for a disc around a point.
ERROR_DIMENSION = {"F": 1, "E": 1, "H": 2, "P": 2}


@dataclass(frozen=True)
class Significance:
    """Best a-contrario split of one model's errors.

    log10_nfa: min over k of log10 NFA(k) (+inf when no k > s was possible).
    inliers: the k achieving it (the k matches of smallest error); eps: their largest error,
    in the units of the errors given.
    """

    log10_nfa: float
    inliers: int
    eps: float


_log10_factorial = np.zeros(1)


def _log10_factorials(n: int) -> np.ndarray:
    """log10 m! for m = 0..n (a table grown on demand: matches per pair are a few thousand)."""
    global _log10_factorial
    if _log10_factorial.size <= n:
        size = max(n + 1, 2 * _log10_factorial.size, 1024)
        _log10_factorial = np.r_[0.0, np.cumsum(np.log10(np.arange(1, size, dtype=np.float64)))]
    return _log10_factorial


def log10_binomial(n: np.ndarray | int, k: np.ndarray | int) -> np.ndarray:
    """log10 C(n, k) for integers 0 <= k <= n, elementwise."""
    n = np.asarray(n, np.int64)
    k = np.asarray(k, np.int64)
    table = _log10_factorials(int(n.max()) if n.size else 0)
    return table[n] - table[k] - table[n - k]


def alpha_coefficient(model: str, width: float, height: float) -> float:
    """alpha(eps) / eps**dim for a region of width x height (same units as the errors)."""
    area = max(width * height, 1e-12)
    if ERROR_DIMENSION[model] == 1:
        return 2.0 * float(np.hypot(width, height)) / area
    return float(np.pi) / area


def match_region(*points: np.ndarray, long_side: float) -> tuple[float, float]:
    """(width, height) of the smallest bounding box of the given matched point sets (K, 2), each
    side floored at long_side / 8 (same units as the points).

    The background spreads chance matches over the region matches actually fall in: a box
    smaller than the image makes chance agreement likelier (larger alpha), so with the points of
    both images the smaller box is the conservative choice; the floor keeps a few clustered
    points from making alpha explode.
    """
    boxes = [np.ptp(x, axis=0) for x in points]
    w, h = min(boxes, key=lambda b: b[0] * b[1])
    floor = long_side / 8
    return max(float(w), floor), max(float(h), floor)


def significance(errors: np.ndarray, model: str, width: float, height: float, max_eps: float | None = None) -> Significance:
    """Minimum log10 NFA over k of a model whose match errors are `errors` (n,).

    errors: per-match error (point-line distance for F/E, transfer distance for H, reprojection
    distance for P) in the units of width/height; non-finite errors count as outliers. max_eps:
    errors above it are never counted as inliers (the model's noise scale), None: no cap.
    """
    n = int(errors.size)
    s = SAMPLE_SIZE[model]
    if n <= s:
        return Significance(float("inf"), 0, 0.0)
    e = np.sort(np.where(np.isfinite(errors), errors, np.inf))
    eps = e[s:]  # eps_k = k-th smallest error
    # Sorted, so the usable k (finite eps_k, at most max_eps) are a prefix of length m.
    m = int(np.searchsorted(eps, np.inf, side="left"))
    if max_eps is not None:
        m = min(m, int(np.searchsorted(eps, max_eps, side="right")))
    if m == 0:
        return Significance(float("inf"), 0, 0.0)
    k, eps = np.arange(s + 1, s + 1 + m), eps[:m]
    # A zero error (duplicated point) would give log(0): floor it at a tiny fraction of a unit.
    alpha = np.minimum(alpha_coefficient(model, width, height) * np.maximum(eps, 1e-6) ** ERROR_DIMENSION[model], 1.0)
    log_nfa = (
        np.log10(MODELS_PER_SAMPLE[model] * (n - s))
        + log10_binomial(n, k)
        + log10_binomial(k, s)
        + (k - s) * np.log10(alpha)
    )
    best = int(np.argmin(log_nfa))
    return Significance(float(log_nfa[best]), int(k[best]), float(eps[best]))
