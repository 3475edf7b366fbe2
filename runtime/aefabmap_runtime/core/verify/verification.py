"""Geometric verification of loop-closure candidates (pure: numpy + OpenCV, no I/O; the matching,
match-counting and model-error loops also have compiled forms, runtime/aefabmap_runtime/core/kernels/compiled.py, with the
same results).

A candidate place is accepted when the query frame's keypoints and the place's stored
keypoints admit a well-conditioned two-view geometry whose support is very unlikely to be
a coincidence:

1. Matching (:func:`match_keypoints`): only keypoint pairs that share a visual word are
   compared (the quantiser already did the coarse search, so this costs a few hundred
   descriptor distances instead of N x M), then nearest neighbour by descriptor distance
   with an absolute distance cap and a ratio test against the second-nearest of the same
   word, and mutual best matches.
2. Geometry (:func:`estimate_geometry`): in coordinates scaled so that the image's longer
   side is ``reference_long_side`` units (thresholds then mean the same at any resolution),
   a homography and a fundamental matrix (an essential matrix when the camera is
   calibrated), both by USAC_MAGSAC.
3. Acceptance, per model: well conditioned (runtime/aefabmap_runtime/core/verify/conditioning.py: F/E of rank 2 with
   a clear second singular value; H orientation-preserving and not near-singular; E with
   most inliers in front of both cameras), inliers not on one line in either image, and
   significant: log10 of the number of false alarms (runtime/aefabmap_runtime/core/verify/acontrario.py, an
   a-contrario test in the manner of ORSA/AC-RANSAC) below ``max_log10_nfa``. The NFA
   weighs the inliers against the number of tentative matches, the region they fall in
   and the model (point-to-line or point-to-point), so no inlier bar depends on the
   matcher, the keypoint budget or the resolution.
4. Brute-force retry (``bruteforce=True``): when same-word matches do not pass, all-pairs
   matching (:func:`match_all`) and the same test (its extra chance matches raise n, and
   with it the support the NFA asks for). The detector uses it for its best FAB-MAP
   candidate and for the places its track prior proposes (runtime/aefabmap_runtime/core/detector.py).

Remaining settings were checked on training data only (camvid frames 1-10 s apart in one
drive and synthetic warps/lighting changes of training images are positives; frames of
different drives, Scene-15 images and camvid-vs-Scene-15 pairs are negatives), see
docs/results.md, "Set on training pairs".
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from aefabmap_runtime.errors import ConfigError
from aefabmap_runtime.core.kernels import compiled, native
from aefabmap_runtime.core.verify.acontrario import SAMPLE_SIZE, match_region, significance
from aefabmap_runtime.core.kernels.bits import hamming
from aefabmap_runtime.core.verify.conditioning import (
    enforce_rank2,
    homography_is_plausible,
    minor_axis_extent,
    rank2_fundamental,
)
from aefabmap_runtime.core.features.feature_kinds import DISTANCES
from aefabmap_runtime.core.features.features import MAX_FEATURES
from aefabmap_runtime.core.verify.model_errors import epipolar_errors, transfer_errors
from aefabmap_runtime.core.verify.nearest import nearest_two, unit_rows
from aefabmap_runtime.core.verify.word_matches import match_same_word

#: Word id of a keypoint kept for geometry only (beyond the bundle's keypoint budget, so never
#: quantised): same-word matching skips it, the brute-force retry matches it like any other.
NO_WORD = -1

GEOMETRY_METHODS = ("magsac", "lo-ransac", "ransac")
# OpenCV flag of each method for F, H and E; "ransac": plain RANSAC (cv2.FM_RANSAC for F).
_USAC_FLAGS = {"lo-ransac": cv2.USAC_DEFAULT, "magsac": cv2.USAC_MAGSAC}
MODELS = ("F", "E", "H")
REJECT_REASONS = ("no_evidence", "chance", "degenerate", "collinear", "clustered", "cheirality")


@dataclass(frozen=True)
class VerificationConfig:
    """Settings of geometric verification (all distances in reference units, see below).

    enabled: run verification at all (the detector then reports `verified`).
    keypoints: keypoints per frame extracted, stored and matched for verification (strongest
        first); None: the bundle's budget (`FeatureConfig.max_features`). Only the bundle's
        budget is quantised: FAB-MAP observes those words, as in training, and same-word
        matching uses them; the keypoints beyond it (NO_WORD) are matched by the brute-force
        retry. Set by measurement on training pairs (docs/results.md, "Keypoint budget"): 1000
        ORB keypoints verified more CamVid pairs a few frames apart than 500, 2000 did no better
        than 1000, and no unrelated pair was accepted with any.
    ratio: Lowe ratio test, nearest / second-nearest descriptor distance of the same word.
    ratio_bruteforce: ratio test of brute-force matching (nearest / second-nearest of all
        place keypoints: a stricter test than within one word, where the second-nearest is
        rarer and farther). Brute-force matching returns more matches, chance ones included;
        the a-contrario test accounts for that through n, so it needs no bars of its own.
        0.8 (Lowe's value) was the best of 0.7-1.0 on training pairs (CamVid pairs of one drive
        1/2/3/5/10 frames apart, brute-force matching of 1000 keypoints), for ORB and SIFT alike,
        with no unrelated pair accepted at any value (docs/results.md, "The brute-force retry's
        ratio test").
    max_hamming: binary kinds: largest Hamming distance of a match, in bits per 256 (ORB's
        length; a binary kind of B bits gets max_hamming * B / 256).
    max_l2: float kinds (SIFT): largest L2 distance of (unit-norm) descriptors of a match.
    reference_long_side: geometry runs in coordinates where the image's longer side is this
        many units, so thresholds do not depend on the camera resolution.
    method: the estimator that proposes models: "magsac" (cv2.USAC_MAGSAC: MAGSAC++), "lo-ransac"
        (cv2.USAC_DEFAULT: RANSAC with local optimisation of the best model) or "ransac"
        (cv2.FM_RANSAC / cv2.RANSAC). Acceptance is the same a-contrario test whichever found
        the model; a better estimator finds more true models, and also more chance ones where
        the test's background (matches at random over the image) does not hold. On training pairs
        (`scripts/calibrate_verification.py --method`, 1000 keypoints, CamVid pairs 1/2/3/5/10
        frames apart) "lo-ransac" accepted more true pairs than MAGSAC++ and no unrelated pair.
        It stays an option, not the default: on the corridor validation sequence it published
        one wrong SIFT loop (an H most of whose matches lie on the fisheye's black lens rim,
        which sits at the same pixels in every frame; docs/results.md, "Estimator: MAGSAC++,
        not LO-RANSAC").
    f_threshold: fundamental/essential-matrix noise scale: the estimator's threshold and the
        largest point-to-epipolar-line distance (units, in both images) an inlier may have.
    h_threshold: the same for the homography (larger of forward and backward transfer error).
    max_log10_nfa: acceptance: log10 of the number of false alarms (`acontrario.py`: how many
        times a model this well supported is expected by chance among the matches) must be
        below this. NFA bounds the expected number of chance acceptances per verified pair; a
        run of ~1000 frames verifies up to ~10^4 pairs (track + top-k + retries), so -4 keeps
        the expected number of chance loop closures of a whole run below one. (NFA < 1, the
        textbook default, let unrelated training pairs through, and moving the bar to -4 cost
        almost no training positives: docs/results.md, "Set on training pairs".)
    duplicate_radius: matches that share a duplicate_radius x duplicate_radius cell (ORIGINAL
        pixels) in either image count once (see `distinct_matches`). ORB finds one corner at
        several pyramid levels, and an image upsampled to the 640-px detection scale yields
        several keypoints per native corner; FAST's test circle has a radius of 3 pixels, so
        corners closer than that share their evidence. The a-contrario count assumes
        independent matches, and on training pairs many inliers were such copies
        (docs/results.md, "The criterion"). 0 disables.
    independence: matches whose query keypoints lie closer than `independence` times the
        typical (median) descriptor window radius of the query's keypoints
        (`FeatureKind.window_radius`) count once as well, when that is more than
        duplicate_radius. At half a radius two windows share over two thirds of their pixels,
        so their descriptors, and whether they match, are not independent: several keypoints
        on one object (a ceiling light, a sign) found again on a similar object elsewhere are
        one coincidence, not several. It matters where windows are large against the image
        (SIFT windows span ~5 keypoint sizes; small images upsampled for detection): on the
        corridor validation sequence (160 x 120) the wrong SIFT loops it removed rested on a few
        keypoints of one ceiling fixture (docs/results.md, "Evidence counted once per descriptor
        window"). 0 disables.
    min_inliers / min_inliers_h: floors on the a-contrario inliers of F/E and H (a model with
        fewer is not used as a loop closure whatever its NFA: too few points to trust it).
    min_f_sigma_ratio: F/E must be well conditioned: sigma2 / sigma1 of the Hartley-normalised
        matrix at least this (rank-1 or null matrices, ratio ~0, explain points on a line).
    h_max_scale / h_max_anisotropy: a homography's local map at its inliers must keep
        orientation, scale area by at most h_max_scale (either way) and stretch one axis at most
        h_max_anisotropy times the other (a near-singular H crushes the image onto a line).
    min_extent: the inliers' spread across their principal axis (standard deviation), in
        fractions of the reference long side, in both images: inliers along one line (railings,
        a row of windows, a kerb) do not fix a two-view geometry.
    min_spread: fraction of the `grid` x `grid` cells holding at least one inlier, required
        in both images (0 disables; diagnostics report it anyway).
    camera: pinhole intrinsics (fx, fy, cx, cy) in pixels of the original images: the
        epipolar model is then an essential matrix (cv2.findEssentialMat) whose inliers must
        mostly (`min_cheirality`) lie in front of both cameras (recoverPose). None: F.
    min_cheirality: fraction of E inliers that must triangulate in front of both cameras.
    The conditioning limits are loose by design (they reject impossible models, not weak
    ones): training positives stay well clear of them, and they reject almost no significant
    model there (docs/results.md, "The criterion").
    grid: cells per side of the spread grid.
    max_iters: homography RANSAC iterations cap (an H iteration is cheap).
    f_max_iters: fundamental-matrix iterations cap: a 7-point MAGSAC iteration costs several H
        ones, and pairs that are not loops run to the cap. A true pair's F (after its H failed)
        is found well within it: the lowest cap that verified exactly the same training revisits
        by day and at night as a higher one, with a margin (docs/results.md, "Iteration caps").
    confidence: RANSAC confidence.
    keep_inlier_points: return the inlier point pairs (`GeometryResult.inlier_points`), for
        evaluation evidence (match images); off in the runtime, where nothing reads them.
    upright: every keypoint is also described with its orientation set to 0 and stored so;
        when the brute-force retry of a tracked place fails (the candidate policy asks it for
        the track's places only), it is retried once more with these upright descriptors
        (`verify_pair_bruteforce`), and that test's NFA counts both descriptor forms
        (UPRIGHT_LOG10_TESTS). An oriented descriptor turns its window by an angle estimated
        from the patch, which a small, blurred or strongly foreshortened patch gives poorly:
        a true correspondence seen from a metre or two aside often gets two different angles
        and no match. A camera that keeps its roll (on a robot, mostly) needs no turning, and
        its upright descriptors of one scene point agree where the oriented ones do not; the
        oriented test stays first, so views rolled against each other (a hand-held camera)
        keep their matches. Measured on training pairs (docs/results.md, "Upright descriptors
        in the retry"). Costs one more description of each frame, 32 bytes more per stored ORB
        keypoint, and one more all-pairs match for each tracked place whose retry fails.
    """

    enabled: bool = True
    keypoints: int | None = 1000
    ratio: float = 0.9
    ratio_bruteforce: float = 0.8
    max_hamming: int = 64
    max_l2: float = 0.7
    reference_long_side: float = 640.0
    method: str = "magsac"
    f_threshold: float = 1.5
    h_threshold: float = 8.0
    max_log10_nfa: float = -4.0
    duplicate_radius: float = 3.0
    independence: float = 0.5
    min_inliers: int = 12
    min_inliers_h: int = 8
    min_f_sigma_ratio: float = 0.005
    h_max_scale: float = 4.0
    h_max_anisotropy: float = 6.0
    min_extent: float = 0.01
    min_spread: float = 0.0
    camera: tuple[float, float, float, float] | None = None
    min_cheirality: float = 0.5
    grid: int = 4
    max_iters: int = 1000
    f_max_iters: int = 100
    confidence: float = 0.999
    keep_inlier_points: bool = False
    upright: bool = True

    def __post_init__(self) -> None:
        if self.keypoints is not None and not (8 <= self.keypoints <= MAX_FEATURES):
            raise ConfigError(f"verification keypoints must be None or in [8, {MAX_FEATURES}], got {self.keypoints}")
        if not (0.0 < self.ratio <= 1.0):
            raise ConfigError(f"verification ratio must lie in (0, 1], got {self.ratio}")
        if self.method not in GEOMETRY_METHODS:
            raise ConfigError(f"verification method must be one of {GEOMETRY_METHODS}, got {self.method!r}")
        if self.f_threshold <= 0 or self.h_threshold <= 0 or self.reference_long_side <= 0:
            raise ConfigError("verification thresholds and reference_long_side must be > 0")
        if not (0.0 < self.ratio_bruteforce <= 1.0):
            raise ConfigError(f"verification ratio_bruteforce must lie in (0, 1], got {self.ratio_bruteforce}")
        if self.min_inliers < 8 or self.min_inliers_h < 5:
            raise ConfigError("verification needs min_inliers >= 8 (F/E) and min_inliers_h >= 5 (H)")
        if not (0.0 <= self.min_f_sigma_ratio < 1.0) or self.h_max_scale < 1.0 or self.h_max_anisotropy < 1.0:
            raise ConfigError("verification needs 0 <= min_f_sigma_ratio < 1, h_max_scale >= 1, h_max_anisotropy >= 1")
        if not (0.0 <= self.min_extent < 1.0) or not (0.0 <= self.min_cheirality <= 1.0):
            raise ConfigError("verification min_extent must lie in [0, 1) and min_cheirality in [0, 1]")
        if self.duplicate_radius < 0:
            raise ConfigError(f"verification duplicate_radius must be >= 0, got {self.duplicate_radius}")
        if not (0.0 <= self.independence <= 4.0):
            raise ConfigError(f"verification independence must lie in [0, 4], got {self.independence}")
        if not np.isfinite(self.max_log10_nfa):
            raise ConfigError(f"verification max_log10_nfa must be finite, got {self.max_log10_nfa}")
        if self.camera is not None:
            object.__setattr__(self, "camera", parse_camera(self.camera))
        if not (0.0 <= self.min_spread <= 1.0) or self.grid < 1:
            raise ConfigError("verification min_spread must lie in [0, 1] and grid be >= 1")
        if self.max_iters < 1 or self.f_max_iters < 1 or not (0.0 < self.confidence < 1.0):
            raise ConfigError("verification max_iters must be >= 1 and confidence lie in (0, 1)")


@dataclass
class GeometryResult:
    """Outcome of verifying one (query, place) pair.

    verified: accepted. model: "F", "E" (calibrated camera) or "H" (the one accepted, or the
    most significant one when rejected; None when there were too few matches to fit anything).
    matrix: (3, 3) float64 mapping place -> query (F and E: the fundamental matrix,
    x_q^T F x_p = 0; H: x_q ~ H x_p), in ORIGINAL pixels of each image.
    inliers: a-contrario inliers of `model` (the k matches of smallest error that make it most
    significant); f_inliers / h_inliers: of each model (f_: F or E); matches: putative matches;
    distinct_matches: those left after merging copies at one location (`duplicate_radius`),
    the n of the a-contrario test. inlier_mask: (matches,) bool over the matches given.
    nfa: log10 of the number of false alarms of `model` (inf: no model); f_nfa / h_nfa: of
    each model. f_sigma_ratio: sigma2 / sigma1 of the normalised F/E (0 when not computed:
    F is checked only once it is significant).
    extent: min over both images of the inliers' standard deviation across their principal
    axis, in fractions of the reference long side (0: on a line).
    spread: min over both images of the occupied grid-cell fraction of the inliers of `model`
    (f_spread / h_spread: of each model). reason: "" when verified, else why not, one of
    REJECT_REASONS ("no_evidence": too few matches to fit a model).
    inlier_points: (inliers, 4) float32 rows (x_q, y_q, x_p, y_p) of the inliers of `model` in
    original pixels, only from `verify_pair` with `VerificationConfig.keep_inlier_points`
    (None otherwise).
    rotation / translation: model "E" only (calibrated camera), else None: the pose of the QUERY
    camera in the PLACE camera's frame from the essential matrix (cv2.recoverPose on the E
    inliers, the decomposition that puts most points in front of both cameras).
    rotation (3, 3): R_pq, columns are the query camera's axes in place-camera coordinates (a
    point X_q in query-camera coordinates is R_pq X_q + t_pq in place-camera coordinates);
    translation (3,): the direction of t_pq, the query camera's centre in place-camera
    coordinates, unit length (two views fix no scale). A back-end adds the edge
    T_w_query = T_w_place [R_pq | s t_pq] with the scale s from elsewhere (depth, odometry).
    """

    verified: bool = False
    model: str | None = None
    matrix: np.ndarray | None = None
    inliers: int = 0
    f_inliers: int = 0
    h_inliers: int = 0
    matches: int = 0
    nfa: float = float("inf")
    f_nfa: float = float("inf")
    h_nfa: float = float("inf")
    f_sigma_ratio: float = 0.0
    extent: float = 0.0
    distinct_matches: int = 0
    spread: float = 0.0
    f_spread: float = 0.0
    h_spread: float = 0.0
    reason: str = "no_evidence"
    inlier_mask: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    inlier_points: np.ndarray | None = None
    rotation: np.ndarray | None = None
    translation: np.ndarray | None = None


def parse_camera(value) -> tuple[float, float, float, float]:
    """Pinhole intrinsics from "fx,fy,cx,cy" or a sequence of 4 numbers -> (fx, fy, cx, cy) floats.

    Raises ConfigError unless there are 4 finite numbers with fx, fy > 0.
    """
    parts = value.split(",") if isinstance(value, str) else value
    try:
        cam = tuple(float(v) for v in parts)
    except (TypeError, ValueError):
        raise ConfigError(f"camera must be fx,fy,cx,cy (4 numbers), got {value!r}") from None
    if len(cam) != 4 or not all(np.isfinite(cam)) or cam[0] <= 0 or cam[1] <= 0:
        raise ConfigError(f"camera must be fx,fy,cx,cy with fx, fy > 0, got {value!r}")
    return cam


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


def _distance_cap(distance: str, desc: np.ndarray, c: VerificationConfig) -> float:
    """The match distance cap of one descriptor family (see max_hamming / max_l2)."""
    if distance not in DISTANCES:
        raise ConfigError(f"descriptor distance must be one of {DISTANCES}, got {distance!r}")
    if distance == "hamming":
        return float(c.max_hamming) * (8 * desc.shape[-1]) / 256.0
    return float(c.max_l2)


def match_keypoints(
    q_words: np.ndarray,
    q_desc: np.ndarray,
    p_words: np.ndarray,
    p_desc: np.ndarray,
    config: VerificationConfig | None = None,
    *,
    distance: str,
) -> np.ndarray:
    """Putative matches between a query and a place, restricted to shared visual words.

    q_words (N,), p_words (M,): word ids (NO_WORD: not quantised, skipped); q_desc (N, B) raw
    descriptors (binary kinds: uint8; float kinds: float32, or uint8 in store form, see
    FeatureKind.compress); p_desc likewise (M, B). distance: the feature kind's distance, "hamming" or "l2" (FeatureKind.distance).
    Returns (K, 2) int64 rows (query index, place index): mutual nearest neighbours among
    same-word keypoints that pass the distance cap and the ratio test.
    """
    c = config or VerificationConfig()
    cap = _distance_cap(distance, q_desc, c)
    if q_words.size == 0 or p_words.size == 0:
        return np.zeros((0, 2), np.int64)
    q_words, p_words = np.asarray(q_words, np.int64), np.asarray(p_words, np.int64)
    if distance == "hamming" and compiled.active() == "compiled":
        return match_same_word(q_words, q_desc, p_words, p_desc, cap, c.ratio)  # same matches, one pass
    q_keep, p_keep = np.flatnonzero(q_words != NO_WORD), np.flatnonzero(p_words != NO_WORD)
    qi, pi = _same_word_pairs(q_words[q_keep], p_words[p_keep])
    qi, pi = q_keep[qi], p_keep[pi]
    if qi.size == 0:
        return np.zeros((0, 2), np.int64)
    if distance == "hamming":
        dist = hamming(q_desc[qi], p_desc[pi]).astype(np.float32)
    else:
        dq = unit_rows(q_desc[qi])
        dp = unit_rows(p_desc[pi])
        dist = np.sqrt(np.maximum(((dq - dp) ** 2).sum(axis=1), 0.0)).astype(np.float32)
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


def match_all(
    q_desc: np.ndarray, p_desc: np.ndarray, config: VerificationConfig | None = None, *, distance: str
) -> np.ndarray:
    """Putative matches over all keypoint pairs (no word restriction); distance as `match_keypoints`.

    Each query keypoint's two nearest place keypoints (`nearest.nearest_two`), the
    distance cap and the ratio test, then each place keypoint keeps only its closest query
    keypoint (one-sided, as `match_keypoints`: the reverse nearest-neighbour pass of a full
    mutual check would double the cost). Returns (K, 2) int64 rows (query index, place index).
    """
    c = config or VerificationConfig()
    cap = _distance_cap(distance, q_desc, c)
    if q_desc.shape[0] == 0 or p_desc.shape[0] < 2:
        return np.zeros((0, 2), np.int64)
    d2, i2 = nearest_two(q_desc, p_desc, distance)
    q = np.arange(q_desc.shape[0])
    p = i2[:, 0]
    keep = (d2[:, 0] <= cap) & (d2[:, 0] < c.ratio_bruteforce * d2[:, 1]) & (p >= 0)
    q, p, d1 = q[keep], p[keep], d2[keep, 0]
    if q.size == 0:
        return np.zeros((0, 2), np.int64)
    order = np.lexsort((d1, p))
    q, p = q[order], p[order]
    first = np.r_[True, p[1:] != p[:-1]]
    return np.stack([q[first], p[first]], axis=1).astype(np.int64)


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
    # Lines with a (near) zero normal are undefined: infinite distance, not a clamped one.
    with np.errstate(divide="ignore", invalid="ignore"):
        dq = num / np.hypot(lq[:, 0], lq[:, 1])
        dp = num / np.hypot(lp[:, 0], lp[:, 1])
        d = np.sqrt(0.5 * (dq**2 + dp**2))
    return np.where(np.isfinite(d), d, np.inf)


def estimate_geometry(
    xq: np.ndarray,
    xp: np.ndarray,
    shape_q: tuple[int, int],
    shape_p: tuple[int, int],
    config: VerificationConfig | None = None,
    full: bool = False,
    radius: float | None = None,
    log10_tests: float = 0.0,
) -> GeometryResult:
    """Fit H and F (or E with a camera) to matched points and decide acceptance.

    xq, xp: (K, 2) float matched positions in original pixels of the query / place image;
    shape_q, shape_p: (height, width) of those images. Returned matrices are in original pixels.
    radius: matches closer than this (query pixels; the place side scaled by the image sizes)
    in either image count once (`independence_radius`); None: `duplicate_radius`.
    log10_tests: added to every model's log10 NFA: the other tests of this pair the caller
    made (e.g. the upright retry, one of two descriptor forms tried).

    A model is accepted when it is well conditioned (`conditioning.py`), its inliers are not
    explained by a line in either image, and its a-contrario significance (`acontrario.py`)
    is below `max_log10_nfa`. Staged for speed (full=False): the cheaper homography is tried
    first and accepted at once; the epipolar model only when H failed (costs: docs/results.md,
    "Per frame"). full=True fits both (calibration and diagnostics); acceptance is the same.
    """
    c = config or VerificationConfig()
    sq = c.reference_long_side / max(shape_q)
    sp = c.reference_long_side / max(shape_p)
    nq = np.ascontiguousarray(xq, np.float64) * sq
    np_ = np.ascontiguousarray(xp, np.float64) * sp
    res = GeometryResult(matches=int(xq.shape[0]))
    # One match per location: ORB detects one corner at several pyramid levels (and several
    # keypoints per corner of an image upsampled for detection), and copies
    # of a match agree with any model the original agrees with. The a-contrario count assumes
    # independent matches, so copies must not count twice (in k or in n).
    r_q = c.duplicate_radius if radius is None else radius
    r_p = r_q * max(shape_p) / max(max(shape_q), 1)
    distinct = distinct_matches(nq, np_, r_q * sq, r_p * sp)
    if distinct.size < nq.shape[0]:
        xq, xp, nq, np_ = xq[distinct], xp[distinct], nq[distinct], np_[distinct]
    k = int(nq.shape[0])
    res.distinct_matches = k
    if k <= SAMPLE_SIZE["H"]:
        res.reason = "no_evidence"
        return res
    region = match_region(nq, np_, long_side=c.reference_long_side)
    best_key = (-1, -np.inf)
    best_matrix = None  # res.model's matrix in reference units, converted to pixels at the end

    def consider(name: str, M: np.ndarray, err: np.ndarray, conditioning=None) -> None:
        """Count the model's significant inliers, run the acceptance tests, keep the best model.

        conditioning: None or a callable -> "" (well conditioned) or a reject reason; called
        only for a significant model (it costs more than the NFA).
        """
        nonlocal best_key, best_matrix
        sig = significance(err, name, region[0], region[1], c.h_threshold if name == "H" else c.f_threshold)
        if log10_tests:
            sig = replace(sig, log10_nfa=sig.log10_nfa + log10_tests)
        mask = (err <= sig.eps) if sig.inliers else np.zeros(k, bool)
        n_in = int(mask.sum())
        if name == "H":
            res.h_inliers, res.h_nfa = n_in, sig.log10_nfa
        else:
            res.f_inliers, res.f_nfa = n_in, sig.log10_nfa
        extent = 0.0
        if n_in < (c.min_inliers_h if name == "H" else c.min_inliers) or sig.log10_nfa >= c.max_log10_nfa:
            reason = "chance"
        else:
            reason = conditioning() if conditioning is not None else ""
            extent = min(minor_axis_extent(nq[mask]), minor_axis_extent(np_[mask]))
            if not reason and extent < c.min_extent * c.reference_long_side:
                reason = "collinear"
        spread = None
        if c.min_spread > 0 or full:
            spread = min(grid_spread(xq[mask], shape_q, c.grid), grid_spread(xp[mask], shape_p, c.grid))
            if name == "H":
                res.h_spread = spread
            else:
                res.f_spread = spread
            if not reason and spread < c.min_spread:
                reason = "clustered"
        ok = not reason
        # Prefer an accepted model; then the most significant one (lowest NFA).
        key = (int(ok), -sig.log10_nfa if np.isfinite(sig.log10_nfa) else -1e300)
        if key > best_key:
            best_key = key
            if spread is None:
                spread = min(grid_spread(xq[mask], shape_q, c.grid), grid_spread(xp[mask], shape_p, c.grid))
            res.verified, res.model, res.inliers, res.spread = ok, name, n_in, spread
            res.nfa, res.reason, res.inlier_mask = sig.log10_nfa, reason, mask
            res.extent = extent / c.reference_long_side
            best_matrix = M

    # Fewer matches than a model's inlier floor cannot pass: do not fit it (unless full).
    H = _fit_homography(np_, nq, c) if full or k >= c.min_inliers_h else None
    if H is not None:

        def h_conditioning() -> str:
            inl = err_h <= c.h_threshold
            ok = homography_is_plausible(H, np_[inl], c.h_max_scale, c.h_max_anisotropy)
            return "" if ok else "degenerate"

        err_h = transfer_errors(H, np_, nq)
        consider("H", H, err_h, h_conditioning)
    if (full or not res.verified) and k > SAMPLE_SIZE["F"] and (full or k >= c.min_inliers):
        if c.camera is not None:
            res.f_sigma_ratio = _consider_essential(nq, np_, xq, xp, sq, sp, c, consider, res)
        else:
            F = _fit_fundamental(np_, nq, c)
            if F is not None:
                # Rank 2 enforced before counting inliers; sigma2 / sigma1 of the normalised F
                # checked for a significant F (a rank-1 F explains any points near one line
                # per image, and would be significant for such points).
                F = enforce_rank2(F)

                def f_conditioning() -> str:
                    _, res.f_sigma_ratio = rank2_fundamental(F, nq, np_)
                    return "" if res.f_sigma_ratio >= c.min_f_sigma_ratio else "degenerate"

                consider("F", F, epipolar_errors(F, nq, np_), f_conditioning)
    if res.model is None:
        res.reason = "no_evidence"
        return res
    res.matrix = _to_pixels(res.model, best_matrix, sq, sp)
    if distinct.size < res.matches:
        # Report the mask over all the matches given (copies of a location count as outliers).
        full_mask = np.zeros(res.matches, bool)
        full_mask[distinct[res.inlier_mask]] = True
        res.inlier_mask = full_mask
    return res


def independence_radius(window_radii: np.ndarray, config: VerificationConfig) -> float:
    """Radius (original pixels) within which a query's matches count once (see `independence`).

    window_radii: (N,) descriptor window radius of each query keypoint (`FeatureKind.window_radius`).
    """
    c = config
    if c.independence <= 0 or window_radii.size == 0:
        return float(c.duplicate_radius)
    return max(float(c.duplicate_radius), c.independence * float(np.median(window_radii)))


# Offsets (in cells) of the four grids of `distinct_matches`.
_GRID_OFFSETS = np.array([(0.0, 0.0), (0.5, 0.0), (0.0, 0.5), (0.5, 0.5)])


def distinct_matches(xq: np.ndarray, xp: np.ndarray, radius_q: float, radius_p: float) -> np.ndarray:
    """Indices of matches xq (K, 2) -> xp (K, 2) keeping one per location in EITHER image.

    The a-contrario count treats matches as independent pieces of evidence. Matches that share
    a location in one image are not: copies of one corner (ORB detects it at several pyramid
    levels; an upsampled image gives several keypoints per corner), keypoints whose descriptor
    windows overlap, or several query points sent to one place point, which any model that
    contracts a region onto it "explains". A location is a cell of a radius_q (query) or radius_p
    (place) grid; four grids offset by half a cell, so that two points closer than half a
    radius along each axis always share a cell of one of them (a single grid splits close
    points that straddle a cell border). A match is kept when it is the first of its cell in
    every grid of both images. A radius <= 0 keeps everything. Returns sorted int64 indices.
    """
    k = xq.shape[0]
    if radius_q <= 0 or radius_p <= 0 or k < 2:
        return np.arange(k, dtype=np.int64)
    if compiled.active() == "compiled" and xq.dtype == np.float64 and xp.dtype == np.float64:
        keep = np.ones(k, np.bool_)
        distinct_kernel()(np.ascontiguousarray(xq), np.ascontiguousarray(xp), float(radius_q), float(radius_p),
                          _GRID_OFFSETS, keep)
        return np.flatnonzero(keep).astype(np.int64)
    # One sort for the eight grids: a cell is (x << 15) + y (clipped to 15 bits per axis, ~32k
    # cells a side) with the grid number above bit 30; key * n + position sorts the matches of a
    # cell by position, so the first of each run is the cell's first match (keys < 2^33 and
    # n = 8 k, so no overflow below a billion matches).
    keys = np.empty((8, k), np.int64)
    for g, (x, r) in enumerate(((xq, radius_q), (xp, radius_p))):
        cells = np.clip(np.floor(x[None, :, :] / r + _GRID_OFFSETS[:, None, :]), 0, 2**15 - 1).astype(np.int64)
        grid = np.arange(4 * g, 4 * g + 4, dtype=np.int64)[:, None] << 30
        keys[4 * g: 4 * g + 4] = (cells[..., 0] << 15) + cells[..., 1] + grid
    n = keys.size
    cell, position = np.divmod(np.sort(keys.ravel() * n + np.arange(n, dtype=np.int64)), n)
    first = np.empty(n, bool)
    first[0], first[1:] = True, cell[1:] != cell[:-1]
    firsts = np.zeros(n, bool)
    firsts[position[first]] = True
    return np.flatnonzero(firsts.reshape(8, k).all(axis=0)).astype(np.int64)


@compiled.kernel(native.distinct)
def distinct_kernel():
    """`distinct_matches` compiled (runtime/aefabmap_runtime/core/kernels/compiled.py): the same cells, computed with the
    same float64 operations, and the same rule (a match is kept when no lower-indexed match shares
    its cell in any of the eight grids); one stable sort per grid instead of array passes whose
    call overhead dominated at the tens of matches a candidate has. keep (K,) must start True."""
    def distinct(xq, xp, radius_q, radius_p, offsets, keep):
        k = xq.shape[0]
        keys = np.empty(k, np.int64)
        for g in range(8):
            x, r = (xq, radius_q) if g < 4 else (xp, radius_p)
            ox, oy = offsets[g % 4, 0], offsets[g % 4, 1]
            for i in range(k):
                cx = min(max(np.floor(x[i, 0] / r + ox), 0.0), 32767.0)
                cy = min(max(np.floor(x[i, 1] / r + oy), 0.0), 32767.0)
                keys[i] = (np.int64(cx) << 15) + np.int64(cy)
            order = np.argsort(keys, kind="mergesort")  # stable: a cell's matches by index
            for t in range(1, k):
                if keys[order[t]] == keys[order[t - 1]]:
                    keep[order[t]] = False

    return compiled.numba.njit("void(float64[:, ::1], float64[:, ::1], float64, float64, float64[:, ::1], boolean[::1])",
                               nogil=True, cache=False, boundscheck=False)(distinct)


def _consider_essential(nq, np_, xq, xp, sq, sp, c: VerificationConfig, consider, res: GeometryResult) -> float:
    """Calibrated camera: essential matrix, cheirality-checked, judged as the F it implies.

    When E becomes res's model, res.rotation / res.translation get its relative pose
    (GeometryResult). Returns sigma2 / sigma1 of the normalised matrix (0.0 when no E was found).
    """
    fx, fy, cx, cy = c.camera
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    px_threshold = c.f_threshold / min(sq, sp)  # reference units -> original pixels
    try:
        E, _ = cv2.findEssentialMat(np.ascontiguousarray(xp, np.float64), np.ascontiguousarray(xq, np.float64), K,
                                    _USAC_FLAGS.get(c.method, cv2.RANSAC), c.confidence, px_threshold,
                                    maxIters=c.f_max_iters)
    except cv2.error:
        return 0.0
    if E is not None and E.ndim == 2 and E.shape[0] > 3 and E.shape[1] == 3:
        E = E[:3]  # several stacked solutions: MAGSAC's best comes first
    if E is None or E.shape != (3, 3) or not np.all(np.isfinite(E)):
        return 0.0
    Kinv = np.linalg.inv(K)
    # F in pixels (x_q^T F x_p = 0), then in reference units (x' = s x).
    F_px = Kinv.T @ E @ Kinv
    F = np.diag([1.0 / sq, 1.0 / sq, 1.0]) @ F_px @ np.diag([1.0 / sp, 1.0 / sp, 1.0])
    F, ratio = rank2_fundamental(F, nq, np_)
    err = epipolar_errors(F, nq, np_)
    pose: list[np.ndarray] = []

    def e_conditioning() -> str:
        if ratio < c.min_f_sigma_ratio:
            return "degenerate"
        inl = err <= c.f_threshold
        try:
            # Place = camera 1, query = camera 2: X_q = R X_p + t.
            front, R, t, _ = cv2.recoverPose(E, np.ascontiguousarray(xp[inl], np.float64),
                                             np.ascontiguousarray(xq[inl], np.float64), K)
        except cv2.error:
            front, R, t = 0, None, None
        if R is not None and t is not None:
            pose[:] = [R, t]
        # The points must lie in front of both cameras: most inliers, not a chance few.
        return "" if front >= c.min_cheirality * int(inl.sum()) else "cheirality"

    consider("E", F, err, e_conditioning)
    if res.model == "E" and pose:
        res.rotation, res.translation = relative_pose_from_recover(*pose)
    return ratio


def relative_pose_from_recover(R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """cv2.recoverPose's (R, t) of place (camera 1) -> query (camera 2), X_q = R X_p + t, as the
    query camera's pose in the place frame: (R_pq = R^T (3, 3), unit t_pq = -R^T t (3,))."""
    R_pq = np.asarray(R, np.float64).T
    c = -R_pq @ np.asarray(t, np.float64).reshape(3)
    n = float(np.linalg.norm(c))
    return R_pq, (c / n if n > 0 else c)


def _fit_homography(src: np.ndarray, dst: np.ndarray, c: VerificationConfig) -> np.ndarray | None:
    method = _USAC_FLAGS.get(c.method, cv2.RANSAC)
    try:
        H, _ = cv2.findHomography(src, dst, method, c.h_threshold, maxIters=c.max_iters, confidence=c.confidence)
    except cv2.error:
        # Degenerate samples (e.g. all points collinear) make OpenCV throw: no model.
        return None
    if H is None or H.shape != (3, 3) or not np.all(np.isfinite(H)):
        return None
    return H


def _fit_fundamental(src: np.ndarray, dst: np.ndarray, c: VerificationConfig) -> np.ndarray | None:
    method = _USAC_FLAGS.get(c.method, cv2.FM_RANSAC)
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
    if model in ("F", "E"):
        # x'q^T F x'p = 0  <=>  xq^T (Sq F Sp) xp = 0.
        out = Sq @ M @ Sp
        return out / max(np.linalg.norm(out), 1e-300)
    # x'q ~ H x'p  <=>  xq ~ Sq^-1 H Sp xp.
    out = np.diag([1.0 / sq, 1.0 / sq, 1.0]) @ M @ Sp
    return out / out[2, 2] if abs(out[2, 2]) > 1e-12 else out


def more_significant(g: GeometryResult, other: GeometryResult | None) -> bool:
    """Whether result g should stand in for `other` (None: no result yet): g was accepted, or its
    model is more significant (smaller log10 NFA)."""
    return other is None or g.verified or g.nfa < other.nfa


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
    *,
    distance: str,
    radius: float | None = None,
    q_upright: np.ndarray | None = None,
    p_upright: np.ndarray | None = None,
) -> GeometryResult:
    """Match a query with one place and verify the geometry.

    q_xy (N, 2) / p_xy (M, 2): keypoint positions in original pixels; *_words: word ids;
    *_desc: descriptors and distance: the feature kind's ("hamming" | "l2", see
    `match_keypoints`); shape_*: (height, width) of each image.
    bruteforce: when same-word matching does not pass, retry with all-pairs matching
    (`verify_pair_bruteforce`, with the upright descriptors q_upright (N, B) / p_upright (M, B)
    when both are given).
    radius: the query's `independence_radius` (None: `duplicate_radius`).
    """
    c = config or VerificationConfig()
    pairs = match_keypoints(q_words, q_desc, p_words, p_desc, c, distance=distance)
    res = GeometryResult()
    if pairs.shape[0]:
        res = estimate_geometry(q_xy[pairs[:, 0]], p_xy[pairs[:, 1]], shape_q, shape_p, c, radius=radius)
        _keep_points(res, pairs, q_xy, p_xy, c)
    if res.verified or not bruteforce:
        return res
    retry = verify_pair_bruteforce(q_xy, q_desc, shape_q, p_xy, p_desc, shape_p, c, distance=distance,
                                   radius=radius, q_upright=q_upright, p_upright=p_upright)
    return retry if more_significant(retry, res) else res


#: log10 of the descriptor forms the upright retry is one of (oriented, upright): its NFA counts
#: both tests of the pair (VerificationConfig.upright).
UPRIGHT_LOG10_TESTS = math.log10(2)


def verify_pair_bruteforce(
    q_xy: np.ndarray,
    q_desc: np.ndarray,
    shape_q: tuple[int, int],
    p_xy: np.ndarray,
    p_desc: np.ndarray,
    shape_p: tuple[int, int],
    config: VerificationConfig | None = None,
    *,
    distance: str,
    radius: float | None = None,
    q_upright: np.ndarray | None = None,
    p_upright: np.ndarray | None = None,
) -> GeometryResult:
    """The brute-force retry of `verify_pair` alone (for a place whose same-word check already
    failed, so that only the retry is paid): all-pairs matching of the descriptors; when that
    fails and both sides have upright descriptors (and `config.upright`), all-pairs matching of
    those, whose NFA counts the two forms tried. The more significant result. Arguments as
    `verify_pair`'s."""
    c = config or VerificationConfig()
    res = _all_pairs_geometry(q_xy, q_desc, shape_q, p_xy, p_desc, shape_p, c, distance, radius)
    if res.verified or not c.upright or q_upright is None or p_upright is None:
        return res
    up = _all_pairs_geometry(q_xy, q_upright, shape_q, p_xy, p_upright, shape_p, c, distance, radius,
                             UPRIGHT_LOG10_TESTS)
    return up if more_significant(up, res) else res


def _all_pairs_geometry(q_xy, q_desc, shape_q, p_xy, p_desc, shape_p, c: VerificationConfig, distance: str,
                        radius: float | None, log10_tests: float = 0.0) -> GeometryResult:
    """All-pairs matching of one descriptor form, then `estimate_geometry` (log10_tests passed on)."""
    pairs = match_all(q_desc, p_desc, c, distance=distance)
    if pairs.shape[0] == 0:
        return GeometryResult()
    # Same criterion: the NFA grows with the number of matches, so the extra chance matches of
    # all-pairs matching raise the support a model needs by themselves.
    res = estimate_geometry(q_xy[pairs[:, 0]], p_xy[pairs[:, 1]], shape_q, shape_p, c, radius=radius,
                            log10_tests=log10_tests)
    _keep_points(res, pairs, q_xy, p_xy, c)
    return res


def _keep_points(res: GeometryResult, pairs: np.ndarray, q_xy: np.ndarray, p_xy: np.ndarray, c: VerificationConfig) -> None:
    """Attach the inlier point pairs of res (its mask indexes `pairs`) when the config asks for them."""
    if c.keep_inlier_points and res.inlier_mask.shape[0] == pairs.shape[0]:
        inl = pairs[res.inlier_mask]
        res.inlier_points = np.c_[q_xy[inl[:, 0]], p_xy[inl[:, 1]]].astype(np.float32)
