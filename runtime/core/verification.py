"""Geometric verification of loop-closure candidates (pure: numpy + OpenCV, no I/O).

A candidate place is accepted when the query frame's keypoints and the place's stored
keypoints admit a two-view geometry with enough well-spread inliers:

1. Matching (:func:`match_keypoints`): only keypoint pairs that share a visual word are
   compared (the quantiser already did the coarse search, so this costs a few hundred
   descriptor distances instead of N x M), then nearest neighbour by descriptor distance
   with an absolute distance cap and a ratio test against the second-nearest of the same
   word, and mutual best matches.
2. Geometry (:func:`estimate_geometry`): in coordinates scaled so that the image's longer
   side is ``reference_long_side`` units (thresholds then mean the same at any resolution),
   a robust fundamental matrix (USAC_MAGSAC by default) whose inliers are re-checked with the
   symmetric epipolar distance, and a homography (planar or rotation-only views, where F is
   degenerate). The model with the larger accepted support wins.
3. Acceptance (:func:`verify_pair`): inliers >= ``min_inliers`` (F) or ``min_inliers_h`` (H)
   and the inliers cover at least ``min_spread`` of the image grid cells in BOTH images
   (random or repeated-texture matches that happen to fit cluster in few cells).
4. Brute-force retry (``bruteforce=True``): when same-word matches do not pass, all-pairs
   matching (:func:`match_all`) and the same geometry against higher bars
   (``min_inliers_bf`` / ``min_inliers_h_bf``: all-pairs matching gives unrelated images more
   chance matches). The detector uses it for its best FAB-MAP candidate and for the places
   its track prior proposes (runtime/core/detector.py).

Defaults were calibrated on training data (camvid street drives: frames 1-3 s apart are
positives, other drives and scene15 images are negatives; also with the images first reduced
to 240 px, the size of small-board cameras), see the README. Brute-force bars: the worst
unrelated training pair reached H 19 / F 34 inliers (ratio 0.9, worst over both
resolutions), so H 22 / F 40.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from aefabmap.errors import ConfigError

GEOMETRY_METHODS = ("magsac", "ransac")
MODELS = ("F", "H")

# popcount of every byte value: Hamming distance of ORB descriptors via a table look-up.
_POPCOUNT = np.unpackbits(np.arange(256, dtype=np.uint8)[:, None], axis=1).sum(axis=1).astype(np.uint16)


@dataclass(frozen=True)
class VerificationConfig:
    """Settings of geometric verification (all distances in reference units, see below).

    enabled: run verification at all (the detector then reports `verified`).
    top_k: FAB-MAP candidates (best log-likelihood first) tried per frame; the first that
        passes is taken, so a true loop usually costs one candidate.
    bruteforce_fallback: the best `bruteforce_fallback` FAB-MAP candidates get a second try
        with all-pairs descriptor matching (`match_all`, its own ratio and inlier bars) when
        same-word matching did not pass: true matches split across words by quantisation.
        Default 1: on training street pairs 2 s apart it raised acceptance from 64% to 77%
        (same rate of unrelated pairs: none) for ~1.5-2 ms, paid on frames whose top candidate fails.
    bruteforce_track: the same retry for every tracked place (see `track`): on the training
        revisit sequences (camvid, see the README) it raised verified recall of revisits 2 s
        from the first pass from 80% to 86% (240 px: 79% to 86%), no false loop.
    max_keypoints: keypoints per place kept in the store and used for matching (strongest
        first); None keeps every keypoint the extractor gave.
    ratio: Lowe ratio test, nearest / second-nearest descriptor distance of the same word.
    ratio_bruteforce: ratio test of brute-force matching (nearest / second-nearest of all
        place keypoints: a stricter test than within one word, where the second-nearest is
        rarer and farther).
    min_inliers_bf / min_inliers_h_bf: F / H inliers needed when the matches came from
        brute-force matching: it returns more chance matches than same-word matching, so
        unrelated training pairs reach more chance inliers (see the README) and need their own,
        higher bars.
    max_hamming: ORB: largest Hamming distance (bits of 256) of a match.
    max_l2: SIFT: largest L2 distance of (unit-norm) descriptors of a match.
    reference_long_side: geometry runs in coordinates where the image's longer side is this
        many units, so thresholds do not depend on the camera resolution.
    method: "magsac" (cv2.USAC_MAGSAC) or "ransac" (cv2.FM_RANSAC / cv2.RANSAC).
    f_threshold: fundamental-matrix inlier threshold (symmetric epipolar distance, units).
    h_threshold: homography inlier threshold (forward transfer error, units).
    min_inliers: F inliers needed to accept.
    min_inliers_h: H inliers needed to accept (H is a stronger model: a point must land on a
        point, not on a line, so chance inliers are rarer and fewer suffice).
    min_spread: fraction of the `grid` x `grid` cells holding at least one inlier, required
        in both images.
    grid: cells per side of the spread grid.
    max_iters: homography RANSAC iterations cap (an H iteration is cheap: 1000 cost ~0.2 ms).
    f_max_iters: fundamental-matrix iterations cap: a 7-point MAGSAC iteration costs ~5x an H
        one; on training street pairs 300 gave the same inlier counts as 1000 on positives
        and cut the time on negatives (which run to the cap) from ~1.2 to ~0.5 ms.
    confidence: RANSAC confidence.
    track: temporal prior (iBoW-LCD / SeqSLAM style): when the previous query frame was
        verified to stored frame f, the stored frames f+1, ..., f+`track`, then f, are tried
        first, before FAB-MAP's candidates (a revisit continues where the last frame matched;
        it recovers frames whose place FAB-MAP ranks low). Every such candidate must pass the
        same geometric test as any other, so a wrong prior costs time, not precision. 0 disables.
    track_memory: the prior lasts this many query frames after the last verified match
        (frame i - lag verified to f: frames f+lag, ..., f+lag+track-1, f+lag-1 are tried), so one
        frame that fails (motion blur, an occluding bus) does not end the track.
    island: each of the best `island_candidates` FAB-MAP candidates that fails is followed by
        its stored temporal neighbours within +-`island` frames (nearest first; only places
        still in the store). 0 (default) disables it: on training street pairs (same-word
        matching) best-of-island raised acceptance of 1-s pairs from 91% to 96%, but on the
        training revisit sequences, with the track prior and brute-force retry on, it added
        0-1 point for +30% trials per frame (non-loop frames pay 2 * island extra trials).
    island_candidates: how many of the FAB-MAP candidates (best first) get island neighbours.
    max_trials: cap on candidates verified per frame (track + FAB-MAP + island), bounding the
        worst-case cost; None: no cap.
    keep_inlier_points: return the inlier point pairs (`GeometryResult.inlier_points`), for
        evaluation evidence (match images); off in the runtime, where nothing reads them.
    """

    enabled: bool = True
    top_k: int = 5
    bruteforce_fallback: int = 1
    bruteforce_track: bool = True
    max_keypoints: int | None = None
    ratio: float = 0.9
    ratio_bruteforce: float = 0.9
    min_inliers_bf: int = 40
    min_inliers_h_bf: int = 22
    max_hamming: int = 64
    max_l2: float = 0.7
    reference_long_side: float = 640.0
    method: str = "magsac"
    f_threshold: float = 1.5
    h_threshold: float = 8.0
    min_inliers: int = 21
    min_inliers_h: int = 15
    min_spread: float = 0.15
    grid: int = 4
    max_iters: int = 1000
    f_max_iters: int = 300
    confidence: float = 0.999
    track: int = 2
    track_memory: int = 3
    island: int = 0
    island_candidates: int = 1
    max_trials: int | None = None
    keep_inlier_points: bool = False

    def __post_init__(self) -> None:
        if self.track_memory < 1:
            raise ConfigError(f"verification track_memory must be >= 1, got {self.track_memory}")
        if self.track < 0 or self.island < 0 or self.island_candidates < 0:
            raise ConfigError(f"verification track and island must be >= 0, got {self.track}, {self.island}")
        if self.max_trials is not None and self.max_trials < 1:
            raise ConfigError(f"verification max_trials must be None or >= 1, got {self.max_trials}")
        if self.bruteforce_fallback < 0:
            raise ConfigError(f"verification bruteforce_fallback must be >= 0, got {self.bruteforce_fallback}")
        if self.top_k < 1:
            raise ConfigError(f"verification top_k must be >= 1, got {self.top_k}")
        if self.max_keypoints is not None and self.max_keypoints < 8:
            raise ConfigError(f"verification max_keypoints must be None or >= 8, got {self.max_keypoints}")
        if not (0.0 < self.ratio <= 1.0):
            raise ConfigError(f"verification ratio must lie in (0, 1], got {self.ratio}")
        if self.method not in GEOMETRY_METHODS:
            raise ConfigError(f"verification method must be one of {GEOMETRY_METHODS}, got {self.method!r}")
        if self.f_threshold <= 0 or self.h_threshold <= 0 or self.reference_long_side <= 0:
            raise ConfigError("verification thresholds and reference_long_side must be > 0")
        if not (0.0 < self.ratio_bruteforce <= 1.0):
            raise ConfigError(f"verification ratio_bruteforce must lie in (0, 1], got {self.ratio_bruteforce}")
        if self.min_inliers < 8 or self.min_inliers_h < 4 or self.min_inliers_bf < 8 or self.min_inliers_h_bf < 4:
            raise ConfigError("verification needs min_inliers >= 8 (F) and min_inliers_h >= 4 (H)")
        if not (0.0 <= self.min_spread <= 1.0) or self.grid < 1:
            raise ConfigError("verification min_spread must lie in [0, 1] and grid be >= 1")
        if self.max_iters < 1 or self.f_max_iters < 1 or not (0.0 < self.confidence < 1.0):
            raise ConfigError("verification max_iters must be >= 1 and confidence lie in (0, 1)")


@dataclass
class GeometryResult:
    """Outcome of verifying one (query, place) pair.

    verified: accepted. model: "F" or "H" (the one accepted, or the better one when rejected;
    None when there were too few matches to fit anything). matrix: (3, 3) float64 mapping place
    -> query (F: x_q^T F x_p = 0; H: x_q ~ H x_p), in ORIGINAL pixels of each image.
    inliers: inliers of `model`; f_inliers / h_inliers: of each model; matches: putative
    matches; spread: min over both images of the occupied grid-cell fraction of the inliers
    of `model` (f_spread / h_spread: of each model). inlier_points: (inliers, 4) float32 rows
    (x_q, y_q, x_p, y_p) of the inliers of `model` in original pixels, only from `verify_pair`
    with `VerificationConfig.keep_inlier_points` (None otherwise).
    """

    verified: bool = False
    model: str | None = None
    matrix: np.ndarray | None = None
    inliers: int = 0
    f_inliers: int = 0
    h_inliers: int = 0
    matches: int = 0
    spread: float = 0.0
    f_spread: float = 0.0
    h_spread: float = 0.0
    inlier_mask: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    inlier_points: np.ndarray | None = None


def hamming_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamming distance between rows a[k] and b[k] of two (P, 32) uint8 arrays -> (P,) int32."""
    return _POPCOUNT[np.bitwise_xor(a, b)].sum(axis=1, dtype=np.int32)


def _same_word_pairs(q_words: np.ndarray, p_words: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """All (query index, place index) pairs whose word ids are equal, as two int64 arrays."""
    order = np.argsort(p_words, kind="stable")
    sorted_words = p_words[order]
    lo = np.searchsorted(sorted_words, q_words, side="left")
    hi = np.searchsorted(sorted_words, q_words, side="right")
    counts = hi - lo
    total = int(counts.sum())
    if total == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    qi = np.repeat(np.arange(q_words.size, dtype=np.int64), counts)
    # Offsets within each run: arange(total) minus the run's start in the flat array.
    run_start = np.repeat(np.cumsum(counts) - counts, counts)
    pi = order[np.repeat(lo, counts) + (np.arange(total) - run_start)]
    return qi, pi.astype(np.int64)


def match_keypoints(
    q_words: np.ndarray,
    q_desc: np.ndarray,
    p_words: np.ndarray,
    p_desc: np.ndarray,
    config: VerificationConfig | None = None,
) -> np.ndarray:
    """Putative matches between a query and a place, restricted to shared visual words.

    q_words (N,), p_words (M,): word ids; q_desc (N, 32) uint8 ORB or (N, 128) SIFT (float32,
    or uint8 as stored, see `compress_descriptors`); p_desc likewise (M, ...).
    Returns (K, 2) int64 rows (query index, place index): mutual nearest neighbours among
    same-word keypoints that pass the distance cap and the ratio test.
    """
    c = config or VerificationConfig()
    if q_words.size == 0 or p_words.size == 0:
        return np.zeros((0, 2), np.int64)
    qi, pi = _same_word_pairs(np.asarray(q_words, np.int64), np.asarray(p_words, np.int64))
    if qi.size == 0:
        return np.zeros((0, 2), np.int64)
    if q_desc.dtype == np.uint8 and q_desc.shape[1] == 32:
        dist = hamming_rows(q_desc[qi], p_desc[pi]).astype(np.float32)
        cap = float(c.max_hamming)
    else:
        dq = _as_unit_float(q_desc[qi])
        dp = _as_unit_float(p_desc[pi])
        dist = np.sqrt(np.maximum(((dq - dp) ** 2).sum(axis=1), 0.0)).astype(np.float32)
        cap = float(c.max_l2)
    # Sort pairs by (query, distance): the first pair of each query is its nearest neighbour.
    order = np.lexsort((dist, qi))
    qi, pi, dist = qi[order], pi[order], dist[order]
    first = np.r_[True, qi[1:] != qi[:-1]]
    starts = np.flatnonzero(first)
    best_q, best_p, d1 = qi[starts], pi[starts], dist[starts]
    # Second-nearest of the same query (inf when the word held one place keypoint).
    has_second = np.r_[starts[1:] - starts[:-1] > 1, qi.size - starts[-1] > 1]
    d2 = np.full(starts.size, np.inf, np.float32)
    d2[has_second] = dist[starts[has_second] + 1]
    keep = (d1 <= cap) & (d1 < c.ratio * d2)
    best_q, best_p, d1 = best_q[keep], best_p[keep], d1[keep]
    if best_q.size == 0:
        return np.zeros((0, 2), np.int64)
    # Mutual: each place keypoint keeps only its closest query keypoint.
    order = np.lexsort((d1, best_p))
    best_q, best_p = best_q[order], best_p[order]
    first = np.r_[True, best_p[1:] != best_p[:-1]]
    return np.stack([best_q[first], best_p[first]], axis=1)


def match_all(q_desc: np.ndarray, p_desc: np.ndarray, config: VerificationConfig | None = None) -> np.ndarray:
    """Putative matches over all keypoint pairs (no word restriction).

    Each query keypoint's two nearest place keypoints (one OpenCV batchDistance pass), the
    distance cap and the ratio test, then each place keypoint keeps only its closest query
    keypoint (one-sided, as `match_keypoints`: the reverse nearest-neighbour pass of a full
    mutual check would double the cost). Returns (K, 2) int64 rows (query index, place index).
    """
    c = config or VerificationConfig()
    if q_desc.shape[0] == 0 or p_desc.shape[0] < 2:
        return np.zeros((0, 2), np.int64)
    if q_desc.dtype == np.uint8 and q_desc.shape[1] == 32:
        a, b, norm, cap = np.ascontiguousarray(q_desc), np.ascontiguousarray(p_desc), cv2.NORM_HAMMING, float(c.max_hamming)
        dtype = cv2.CV_32S
    else:
        a, b, norm, cap = _as_unit_float(q_desc), _as_unit_float(p_desc), cv2.NORM_L2, float(c.max_l2)
        dtype = cv2.CV_32F
    # OpenCV's batchDistance: vectorised popcount / L2, the two nearest per query row.
    d2, i2 = cv2.batchDistance(a, b, dtype, normType=norm, K=2)
    d2 = d2.astype(np.float32)
    q = np.arange(a.shape[0])
    p = i2[:, 0].astype(np.int64)
    keep = (d2[:, 0] <= cap) & (d2[:, 0] < c.ratio_bruteforce * d2[:, 1]) & (p >= 0)
    q, p, d1 = q[keep], p[keep], d2[keep, 0]
    if q.size == 0:
        return np.zeros((0, 2), np.int64)
    order = np.lexsort((d1, p))
    q, p = q[order], p[order]
    first = np.r_[True, p[1:] != p[:-1]]
    return np.stack([q[first], p[first]], axis=1).astype(np.int64)


def _as_unit_float(desc: np.ndarray) -> np.ndarray:
    """Descriptors (float or stored uint8) -> float32 rows of unit L2 norm."""
    d = desc.astype(np.float32)
    return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)


def compress_descriptors(desc: np.ndarray) -> np.ndarray:
    """Store form of descriptors: ORB unchanged (N, 32) uint8; SIFT/RootSIFT (N, 128) float -> uint8.

    Unit-norm float descriptors are scaled so their largest component maps to 255 per row
    (matching renormalises, so a per-row scale loses nothing but rounding: 128 B instead of 512 B).
    """
    if desc.dtype == np.uint8:
        return np.ascontiguousarray(desc)
    d = np.asarray(desc, np.float32)
    peak = np.maximum(d.max(axis=1, keepdims=True), 1e-12)
    return np.clip(np.rint(d / peak * 255.0), 0, 255).astype(np.uint8)


def grid_spread(points: np.ndarray, shape_hw: tuple[float, float], grid: int) -> float:
    """Fraction of the grid x grid cells over the image holding at least one of points (K, 2)."""
    if points.shape[0] == 0:
        return 0.0
    h, w = float(shape_hw[0]), float(shape_hw[1])
    gx = np.minimum((np.maximum(points[:, 0], 0) * (grid / max(w, 1e-6))).astype(np.int64), grid - 1)
    gy = np.minimum((np.maximum(points[:, 1], 0) * (grid / max(h, 1e-6))).astype(np.int64), grid - 1)
    occupied = np.zeros(grid * grid, bool)
    occupied[gy * grid + gx] = True
    return float(occupied.sum()) / (grid * grid)


def symmetric_epipolar_distance(F: np.ndarray, xq: np.ndarray, xp: np.ndarray) -> np.ndarray:
    """Symmetric epipolar distance (K,) of matches xp -> xq (K, 2) under x_q^T F x_p = 0.

    sqrt of the mean of the squared point-line distances in both images: comparable to a
    reprojection error in the same units as the points.
    """
    hp = np.c_[xp, np.ones(len(xp))]
    hq = np.c_[xq, np.ones(len(xq))]
    lq = hp @ F.T  # epipolar lines in the query image
    lp = hq @ F  # epipolar lines in the place image
    num = np.abs(np.sum(hq * lq, axis=1))
    dq = num / np.maximum(np.hypot(lq[:, 0], lq[:, 1]), 1e-12)
    dp = num / np.maximum(np.hypot(lp[:, 0], lp[:, 1]), 1e-12)
    return np.sqrt(0.5 * (dq**2 + dp**2))


def estimate_geometry(
    xq: np.ndarray,
    xp: np.ndarray,
    shape_q: tuple[int, int],
    shape_p: tuple[int, int],
    config: VerificationConfig | None = None,
    full: bool = False,
) -> GeometryResult:
    """Fit H and F to matched points and decide acceptance.

    xq, xp: (K, 2) float matched positions in original pixels of the query / place image;
    shape_q, shape_p: (height, width) of those images. Returned matrices are in original pixels.

    Staged for speed (full=False): fewer than `min_inliers_h` matches cannot pass and fit
    nothing; the homography (MAGSAC: ~0.2 ms) is tried first and accepted at once; the
    fundamental matrix (~1.5 ms) only when H failed and there are >= `min_inliers` matches.
    full=True fits both models (calibration and diagnostics); acceptance is the same.
    """
    c = config or VerificationConfig()
    k = int(xq.shape[0])
    res = GeometryResult(matches=k)
    if k < min(c.min_inliers_h, c.min_inliers) and not full:
        return res
    sq = c.reference_long_side / max(shape_q)
    sp = c.reference_long_side / max(shape_p)
    nq = np.ascontiguousarray(xq, np.float64) * sq
    np_ = np.ascontiguousarray(xp, np.float64) * sp
    best_margin = -np.inf

    def consider(name: str, M: np.ndarray, mask: np.ndarray, need: int) -> None:
        nonlocal best_margin
        spread = min(grid_spread(xq[mask], shape_q, c.grid), grid_spread(xp[mask], shape_p, c.grid))
        n_in = int(mask.sum())
        if name == "F":
            res.f_inliers, res.f_spread = n_in, spread
        else:
            res.h_inliers, res.h_spread = n_in, spread
        ok = n_in >= need and spread >= c.min_spread
        # Prefer an accepted model; among equals, the one with the most support over its bar.
        margin = (1e9 if ok else 0.0) + n_in / need
        if margin > best_margin:
            best_margin = margin
            res.verified, res.model, res.inliers, res.spread = ok, name, n_in, spread
            res.inlier_mask = mask
            res.matrix = _to_pixels(name, M, sq, sp)

    if k >= 4:
        H = _fit_homography(np_, nq, c)
        if H is not None:
            proj = np.c_[np_, np.ones(k)] @ H.T
            with np.errstate(divide="ignore", invalid="ignore"):
                proj = proj[:, :2] / proj[:, 2:3]
            err = np.linalg.norm(proj - nq, axis=1)
            consider("H", H, np.isfinite(err) & (err <= c.h_threshold), c.min_inliers_h)
    if (full or not res.verified) and k >= max(8, c.min_inliers if not full else 8):
        F = _fit_fundamental(np_, nq, c)
        if F is not None:
            # MAGSAC's mask is a soft decision: re-check every match with one crisp test.
            consider("F", F, symmetric_epipolar_distance(F, nq, np_) <= c.f_threshold, c.min_inliers)
    return res


def _fit_homography(src: np.ndarray, dst: np.ndarray, c: VerificationConfig) -> np.ndarray | None:
    method = cv2.USAC_MAGSAC if c.method == "magsac" else cv2.RANSAC
    try:
        H, _ = cv2.findHomography(src, dst, method, c.h_threshold, maxIters=c.max_iters, confidence=c.confidence)
    except cv2.error:
        # Degenerate samples (e.g. all points collinear) make OpenCV throw: no model.
        return None
    if H is None or H.shape != (3, 3) or not np.all(np.isfinite(H)):
        return None
    return H


def _fit_fundamental(src: np.ndarray, dst: np.ndarray, c: VerificationConfig) -> np.ndarray | None:
    method = cv2.USAC_MAGSAC if c.method == "magsac" else cv2.FM_RANSAC
    try:
        F, _ = cv2.findFundamentalMat(src, dst, method, c.f_threshold, c.confidence, c.f_max_iters)
    except cv2.error:
        return None
    # OpenCV may return several stacked 3x3 solutions (7-point) or none.
    if F is None or F.shape != (3, 3) or not np.all(np.isfinite(F)):
        return None
    return F


def _to_pixels(model: str, M: np.ndarray, sq: float, sp: float) -> np.ndarray:
    """Matrix estimated on scaled points (x' = s x) -> the same relation in original pixels."""
    Sq = np.diag([sq, sq, 1.0])
    Sp = np.diag([sp, sp, 1.0])
    if model == "F":
        # x'q^T F x'p = 0  <=>  xq^T (Sq F Sp) xp = 0.
        out = Sq @ M @ Sp
        return out / max(np.linalg.norm(out), 1e-300)
    # x'q ~ H x'p  <=>  xq ~ Sq^-1 H Sp xp.
    out = np.diag([1.0 / sq, 1.0 / sq, 1.0]) @ M @ Sp
    return out / out[2, 2] if abs(out[2, 2]) > 1e-12 else out


def verify_pair(
    q_xy: np.ndarray,
    q_words: np.ndarray,
    q_desc: np.ndarray,
    shape_q: tuple[int, int],
    p_xy: np.ndarray,
    p_words: np.ndarray,
    p_desc: np.ndarray,
    shape_p: tuple[int, int],
    config: VerificationConfig | None = None,
    bruteforce: bool = False,
) -> GeometryResult:
    """Match a query with one place and verify the geometry.

    q_xy (N, 2) / p_xy (M, 2): keypoint positions in original pixels; *_words: word ids;
    *_desc: descriptors (see `match_keypoints`); shape_*: (height, width) of each image.
    bruteforce: when same-word matching does not pass, retry with all-pairs matching.
    """
    c = config or VerificationConfig()
    pairs = match_keypoints(q_words, q_desc, p_words, p_desc, c)
    res = GeometryResult()
    if pairs.shape[0]:
        res = estimate_geometry(q_xy[pairs[:, 0]], p_xy[pairs[:, 1]], shape_q, shape_p, c)
        _keep_points(res, pairs, q_xy, p_xy, c)
    if res.verified or not bruteforce:
        return res
    pairs = match_all(q_desc, p_desc, c)
    if pairs.shape[0] == 0:
        return res
    cb = replace(c, min_inliers=c.min_inliers_bf, min_inliers_h=c.min_inliers_h_bf)
    retry = estimate_geometry(q_xy[pairs[:, 0]], p_xy[pairs[:, 1]], shape_q, shape_p, cb)
    _keep_points(retry, pairs, q_xy, p_xy, c)
    return retry if retry.verified or retry.inliers > res.inliers else res


def _keep_points(res: GeometryResult, pairs: np.ndarray, q_xy: np.ndarray, p_xy: np.ndarray, c: VerificationConfig) -> None:
    """Attach the inlier point pairs of res (its mask indexes `pairs`) when the config asks for them."""
    if c.keep_inlier_points and res.inlier_mask.shape[0] == pairs.shape[0]:
        inl = pairs[res.inlier_mask]
        res.inlier_points = np.c_[q_xy[inl[:, 0]], p_xy[inl[:, 1]]].astype(np.float32)
