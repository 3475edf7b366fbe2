"""Attacks on geometric verification: degenerate and chance models must not verify."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from aefabmap_runtime.core.verify.acontrario import log10_binomial, significance
from aefabmap_runtime.core.verify.conditioning import (
    homography_is_plausible,
    rank2_fundamental,
)
from aefabmap_runtime.core.features.feature_kinds import get_kind
from aefabmap_runtime.core.verify.model_errors import epipolar_errors
from aefabmap_runtime.core.verify.verification import (
    GEOMETRY_METHODS,
    VerificationConfig,
    distinct_matches,
    independence_radius,
    estimate_geometry,
    match_all,
    parse_camera,
)

K = np.array([[400.0, 0, 320], [0, 400.0, 240], [0, 0, 1]])


def two_views(n=200, seed=0, noise=0.3):
    """Matches of random 3-D points (not planar) seen from two poses, 640 x 480 pixels."""
    rng = np.random.default_rng(seed)
    X = np.c_[rng.uniform(-4, 4, n), rng.uniform(-3, 3, n), rng.uniform(6, 20, n)]
    R, _ = cv2.Rodrigues(np.array([0.0, 0.15, 0.02]))
    t = np.array([1.0, 0.1, 0.3])

    def project(P):
        x = P @ K.T
        return x[:, :2] / x[:, 2:]

    return project(X @ R.T + t) + rng.normal(0, noise, (n, 2)), project(X)


def test_points_on_a_line_in_each_image_do_not_verify():
    """The railing attack: matches along one line per image fit a rank-1 F exactly."""
    rng = np.random.default_rng(1)
    n = 80
    # A railing crossing both images (slightly tilted), matched to the wrong rails at random.
    xs_p, xs_q = rng.uniform(20, 620, n), rng.uniform(20, 620, n)
    xp = np.c_[xs_p, 300 + 0.1 * xs_p + rng.normal(0, 0.4, n)]
    xq = np.c_[xs_q, 200 - 0.05 * xs_q + rng.normal(0, 0.4, n)]
    g = estimate_geometry(xq, xp, (480, 640), (480, 640), VerificationConfig(), full=True)
    assert not g.verified and g.reason in ("degenerate", "collinear", "chance")


def test_a_rank_one_or_null_fundamental_matrix_is_rejected():
    xq, xp = two_views()
    rank1 = np.outer([0.0, 1.0, -200.0], [0.0, 1.0, -300.0])
    _, ratio = rank2_fundamental(rank1, xq, xp)
    assert ratio < 1e-9
    F_null = np.full((3, 3), 1e-24)
    # A (numerically) null F gives no epipolar lines: no point may count as its inlier.
    assert np.all(np.isinf(epipolar_errors(F_null * 0.0, xq, xp)))
    # A true F keeps a clear second singular value after normalisation.
    g = estimate_geometry(xq, xp, (480, 640), (480, 640), VerificationConfig(min_inliers_h=1000), full=True)
    assert g.verified and g.model == "F" and g.f_sigma_ratio > 0.05 and g.nfa < -100


def test_random_matches_are_chance():
    """Uniform random matches: whatever models are fitted, NFA >= 1 (log10 >= 0)."""
    for seed in range(5):
        rng = np.random.default_rng(seed)
        xq = rng.uniform(0, [640, 480], (150, 2))
        xp = rng.uniform(0, [640, 480], (150, 2))
        g = estimate_geometry(xq, xp, (480, 640), (480, 640), VerificationConfig(), full=True)
        assert not g.verified and g.f_nfa >= 0 and g.h_nfa >= 0, (seed, g.f_nfa, g.h_nfa)


@pytest.mark.parametrize("method", GEOMETRY_METHODS)
def test_every_estimator_is_judged_by_the_same_test(method):
    """Whichever estimator proposes the models, a true 3-D scene verifies as F and chance or
    degenerate matches do not."""
    cfg = VerificationConfig(method=method, min_inliers_h=1000)
    xq, xp = two_views(seed=2)
    g = estimate_geometry(xq, xp, (480, 640), (480, 640), cfg)
    assert g.verified and g.model == "F" and g.nfa < -50, (method, g.reason, g.nfa)
    rng = np.random.default_rng(7)
    xq, xp = rng.uniform(0, [640, 480], (150, 2)), rng.uniform(0, [640, 480], (150, 2))
    assert not estimate_geometry(xq, xp, (480, 640), (480, 640), VerificationConfig(method=method), full=True).verified
    xs_p, xs_q = rng.uniform(20, 620, 80), rng.uniform(20, 620, 80)
    line_p = np.c_[xs_p, 300 + 0.1 * xs_p + rng.normal(0, 0.4, 80)]
    line_q = np.c_[xs_q, 200 - 0.05 * xs_q + rng.normal(0, 0.4, 80)]
    assert not estimate_geometry(line_q, line_p, (480, 640), (480, 640), VerificationConfig(method=method),
                                 full=True).verified


def test_significance_grows_with_support_and_counts_the_matches():
    errors = np.r_[np.full(30, 0.3), np.full(70, 1e9)]
    few_matches = significance(errors[:40], "F", 640, 480, 1.5)
    many_matches = significance(errors, "F", 640, 480, 1.5)
    # The same 30 inliers are less surprising among more tentative matches.
    assert few_matches.log10_nfa < many_matches.log10_nfa < -10
    assert many_matches.inliers == 30
    assert significance(np.full(7, 0.1), "F", 640, 480).log10_nfa == float("inf")  # k must exceed s
    assert abs(float(log10_binomial(60, 15)) - math.log10(math.comb(60, 15))) < 1e-9


def test_a_pose_from_3d_points_is_judged_by_its_reprojection_errors():
    """Model "P" (a PnP pose, 5-point sample, point-to-point reprojection error), as the SLAM
    tool's proposals use it: errors spread over the image are chance, a tight cluster is not,
    and it needs more support than a homography (one more point in its sample)."""
    rng = np.random.default_rng(0)
    # A pose that explains nothing: each match lands anywhere in the image.
    chance = np.linalg.norm(rng.uniform((0, 0), (640, 480), (3000, 2)) - rng.uniform((0, 0), (640, 480), (3000, 2)), axis=1)
    assert significance(chance, "P", 640, 480, 40.0).log10_nfa > 0
    spread = rng.uniform(5, 400, 300)
    tight = np.r_[np.full(20, 1.0), spread[:280]]
    pose, homography = significance(tight, "P", 640, 480, 3.0), significance(tight, "H", 640, 480, 3.0)
    assert pose.inliers == 20 and pose.log10_nfa < -4
    assert homography.log10_nfa < pose.log10_nfa


def test_a_folding_homography_is_implausible():
    pts = np.random.default_rng(0).uniform(0, 600, (50, 2))
    assert homography_is_plausible(np.eye(3), pts, 4.0, 6.0)
    mirror = np.diag([-1.0, 1.0, 1.0])
    assert not homography_is_plausible(mirror, pts, 4.0, 6.0)
    crush = np.diag([1.0, 0.01, 1.0])
    assert not homography_is_plausible(crush, pts, 4.0, 6.0)


def test_calibrated_camera_uses_the_essential_matrix():
    xq, xp = two_views()
    cfg = VerificationConfig(min_inliers_h=1000, camera=(400.0, 400.0, 320.0, 240.0))
    g = estimate_geometry(xq, xp, (480, 640), (480, 640), cfg)
    assert g.verified and g.model == "E" and g.inliers > 180
    assert np.median(epipolar_errors(g.matrix, xq, xp)) < 1.0
    assert parse_camera("400,400,320,240") == (400.0, 400.0, 320.0, 240.0)


def test_points_behind_a_camera_fail_the_cheirality_check():
    """Epipolar geometry holds exactly, but no pose puts most points in front of both cameras.

    A third of the points lie in front of both cameras, a third behind both, a third between
    them (in front of the place camera, behind the query camera): each of the four poses an
    essential matrix admits explains only about a third.
    """
    rng = np.random.default_rng(3)
    z = np.r_[rng.uniform(-20, -6, 60), rng.uniform(2, 8, 60), rng.uniform(14, 30, 60)]
    X = np.c_[rng.uniform(-0.4, 0.4, 180) * np.abs(z), rng.uniform(-0.3, 0.3, 180) * np.abs(z), z]
    Xq = X - np.array([0.0, 0.0, 10.0])  # the query camera 10 m ahead, same orientation

    def project(P):
        x = P @ K.T
        return x[:, :2] / x[:, 2:]

    xq, xp = project(Xq), project(X)
    cfg = VerificationConfig(min_inliers_h=1000, camera=(400.0, 400.0, 320.0, 240.0))
    g = estimate_geometry(xq, xp, (480, 640), (480, 640), cfg, full=True)
    assert not g.verified and g.reason == "cheirality", (g.model, g.reason, g.nfa)


# --- real data (skipped when absent) ---------------------------------------------------------


@pytest.mark.slow
def test_lip6_233_to_41_is_not_verified(lip6):
    """Two different streets that passed the old brute-force retry on a rank-1 F (56 'inliers')."""
    from aefabmap_runtime.adapters.frames import load_image
    from aefabmap_runtime.core.features.features import FeatureConfig, FeatureExtractor
    from aefabmap_runtime.core.verify.verification import verify_pair

    q_path, p_path = lip6 / "outdoor_kennedylong_000233.jpg", lip6 / "outdoor_kennedylong_000041.jpg"
    if not (q_path.exists() and p_path.exists()):
        pytest.skip("lip6 frames 233/41 not found")
    cfg = VerificationConfig()
    for fc in (FeatureConfig(kind="orb", max_features=500), FeatureConfig(kind="orb", max_features=1000)):
        ex = FeatureExtractor(fc)
        fq, fp = ex.extract(load_image(q_path)), ex.extract(load_image(p_path))
        pairs = match_all(fq.descriptors, fp.descriptors, cfg, distance="hamming")
        g = estimate_geometry(fq.keypoints[pairs[:, 0]], fp.keypoints[pairs[:, 1]], fq.image_shape, fp.image_shape,
                              cfg, full=True)
        assert not g.verified, (g.model, g.inliers, g.nfa)
        one = np.zeros(len(fq), np.int64)
        g = verify_pair(fq.keypoints, one, fq.descriptors, fq.image_shape,
                        fp.keypoints, np.zeros(len(fp), np.int64), fp.descriptors, fp.image_shape, cfg, bruteforce=True,
                        distance="hamming")
        assert not g.verified, (g.model, g.inliers, g.nfa)


def test_copies_of_a_match_count_once():
    """ORB finds one corner at several pyramid levels: its copies must not add significance."""
    xq, xp = two_views(n=60, seed=5)
    rng = np.random.default_rng(5)
    jitter = lambda x: x + rng.normal(0, 0.2, x.shape)  # noqa: E731
    xq3, xp3 = np.r_[xq, jitter(xq), jitter(xq)], np.r_[xp, jitter(xp), jitter(xp)]
    cfg = VerificationConfig(min_inliers_h=1000)
    once = estimate_geometry(xq, xp, (480, 640), (480, 640), cfg)
    copied = estimate_geometry(xq3, xp3, (480, 640), (480, 640), cfg)
    counted = estimate_geometry(xq3, xp3, (480, 640), (480, 640), VerificationConfig(min_inliers_h=1000, duplicate_radius=0))
    assert copied.distinct_matches < 0.5 * len(xq3) and copied.inlier_mask.shape == (len(xq3),)
    # Counting the copies would claim far more significance than the 60 points carry.
    assert counted.nfa < copied.nfa - 20
    assert abs(copied.nfa - once.nfa) < 0.5 * abs(once.nfa)


def one_object_and_chance(seed=0):
    """160 x 120 views: 22 chance matches, and 8 matches that agree on one shift (3, 2.6) px,
    6 of them keypoints 2.5 px apart on one small object (a ceiling fixture found again on a
    similar fixture elsewhere: the corridor validation sequence's wrong SIFT loops)."""
    rng = np.random.default_rng(seed)
    xq = np.c_[rng.uniform(0, 160, 22), rng.uniform(0, 120, 22)]
    xp = np.c_[rng.uniform(0, 160, 22), rng.uniform(0, 120, 22)]
    obj = np.array([[112, 5], [114.5, 5], [117, 5], [112, 7.5], [114.5, 7.5], [117, 7.5], [8, 44], [60, 100]], float)
    shifted = obj + [3.0, 2.6] + rng.normal(0, 0.1, obj.shape)
    return np.r_[xq, shifted], np.r_[xp, obj]


def test_keypoints_on_one_object_count_once():
    xq, xp = one_object_and_chance()
    cfg = VerificationConfig()
    # Counted as 8 independent matches, the shift is far beyond chance...
    as_points = estimate_geometry(xq, xp, (120, 160), (120, 160), cfg, radius=1.0)
    assert as_points.verified and as_points.inliers == 8
    # ...but the six keypoints whose descriptor windows overlap are one coincidence.
    as_objects = estimate_geometry(xq, xp, (120, 160), (120, 160), cfg, radius=8.0)
    assert not as_objects.verified
    assert as_objects.distinct_matches <= as_points.distinct_matches - 3


def test_close_matches_on_either_side_of_a_cell_border_count_once(kernels):
    # 0.2 px apart across the border x = 6 of a 3-px grid: one location.
    xq = np.array([[5.9, 10.0], [6.1, 10.0], [40.0, 40.0]])
    xp = np.array([[50.0, 50.0], [80.0, 20.0], [90.0, 90.0]])
    assert distinct_matches(xq, xp, 3.0, 3.0).tolist() == [0, 2]
    assert distinct_matches(xp, xq, 3.0, 3.0).tolist() == [0, 2]  # either image
    assert distinct_matches(xq, xp, 0.0, 3.0).tolist() == [0, 1, 2]


def _distinct_by_definition(xq, xp, rq, rp):
    """The rule written out: keep a match when no earlier match shares any of its 8 cells."""
    seen, kept = set(), []
    for i in range(len(xq)):
        cells = {(g, side, int(np.floor(x[i, 0] / r + ox)), int(np.floor(x[i, 1] / r + oy)))
                 for side, (x, r) in enumerate(((xq, rq), (xp, rp)))
                 for g, (ox, oy) in enumerate(((0, 0), (0.5, 0), (0, 0.5), (0.5, 0.5)))}
        if not cells & seen:
            kept.append(i)
        seen |= cells
    return kept


def test_distinct_matches_keeps_the_first_match_of_every_cell(kernels):
    rng = np.random.default_rng(3)
    for trial in range(200):
        k = int(rng.integers(2, 120))
        xq, xp = rng.uniform(0, 300, (k, 2)), rng.uniform(0, 200, (k, 2))
        if trial % 2:
            xq = np.round(xq / 9) * 9  # many shared cells
        rq, rp = rng.uniform(1, 20), rng.uniform(1, 20)
        if trial % 3 == 0:  # points exactly on the borders of the grids and of the offset grids
            rq, xq = 3.0, np.round(xq / 1.5) * 1.5
        assert distinct_matches(xq, xp, rq, rp).tolist() == _distinct_by_definition(xq, xp, rq, rp)


def test_independence_radius_follows_the_descriptor_window():
    orb, sift = get_kind("orb"), get_kind("sift")
    sizes = np.array([2.0, 2.0, 4.0])
    # ORB computes its descriptor inside the keypoint's patch (size = diameter); SIFT's window
    # is 5.3 keypoint sizes in radius.
    assert np.allclose(orb.window_radius(sizes), [1.0, 1.0, 2.0])
    assert np.allclose(sift.window_radius(sizes), [10.6, 10.6, 21.2])
    cfg = VerificationConfig()
    assert independence_radius(sift.window_radius(sizes), cfg) == pytest.approx(0.5 * 10.6)  # median, halved
    assert independence_radius(orb.window_radius(sizes), cfg) == cfg.duplicate_radius  # floored
    assert independence_radius(sift.window_radius(sizes), VerificationConfig(independence=0)) == cfg.duplicate_radius
    assert independence_radius(np.zeros(0), cfg) == cfg.duplicate_radius

def _rot(rvec) -> np.ndarray:
    R, _ = cv2.Rodrigues(np.asarray(rvec, np.float64))
    return R


@pytest.mark.parametrize("rvec, centre", [
    ((0.0, 0.2, 0.05), (1.0, 0.1, -0.5)),    # turn left, move right and back
    ((0.1, -0.3, 0.0), (-0.8, 0.0, 1.5)),    # turn right, move left and forward
])
def test_essential_matrix_gives_the_query_pose_relative_to_the_place(rvec, centre):
    """Place camera at the origin, query camera at `centre` with orientation R_pq (its axes in place
    coordinates): the result's rotation is R_pq and its translation the unit direction of `centre`."""
    rng = np.random.default_rng(5)
    X = np.c_[rng.uniform(-4, 4, 200), rng.uniform(-3, 3, 200), rng.uniform(6, 20, 200)]  # place frame
    R_pq, c = _rot(rvec), np.asarray(centre, np.float64)
    Xq = (X - c) @ R_pq  # R_pq^T (X - c) row by row: the points in query-camera coordinates

    def project(P):
        x = P @ K.T
        return x[:, :2] / x[:, 2:]

    xq, xp = project(Xq) + rng.normal(0, 0.3, (200, 2)), project(X)
    cfg = VerificationConfig(min_inliers_h=1000, camera=(400.0, 400.0, 320.0, 240.0))
    g = estimate_geometry(xq, xp, (480, 640), (480, 640), cfg)
    assert g.verified and g.model == "E"
    angle = np.degrees(np.arccos(np.clip((np.trace(g.rotation.T @ R_pq) - 1) / 2, -1, 1)))
    assert angle < 0.5, angle
    assert abs(np.linalg.norm(g.translation) - 1.0) < 1e-9
    assert np.degrees(np.arccos(np.clip(g.translation @ (c / np.linalg.norm(c)), -1, 1))) < 2.0


def test_only_the_essential_matrix_carries_a_relative_pose():
    xq, xp = two_views()
    for cfg in (VerificationConfig(min_inliers_h=1000), VerificationConfig()):  # F; H or F, no camera
        g = estimate_geometry(xq, xp, (480, 640), (480, 640), cfg)
        assert g.verified and g.model != "E" and g.rotation is None and g.translation is None


@pytest.mark.slow
def test_corridor_106_to_27_on_the_lens_rim_is_not_verified(shared_data):
    """The corridor's fisheye rim: 7 SIFT keypoints on the rim, 0.7-2.4 pixels from where they were
    in a frame of another place, agree with a near-identity homography. LO-RANSAC finds it (8 of
    15 matches, log10 NFA -6.8), which is why it is not the default; the default must not."""
    from aefabmap_runtime.adapters.frames import load_image
    from aefabmap_runtime.core.features.features import FeatureConfig, FeatureExtractor
    from aefabmap_runtime.core.verify.verification import NO_WORD, verify_pair

    images = shared_data / "validation" / "corridor" / "images"
    q_path, p_path = images / "000106.jpg", images / "000027.jpg"
    if not (q_path.exists() and p_path.exists()):
        pytest.skip("corridor frames 106/27 not found")
    kind = get_kind("sift")
    ex = FeatureExtractor(FeatureConfig(kind="sift", max_features=VerificationConfig().keypoints))
    fq, fp = ex.extract(load_image(q_path)), ex.extract(load_image(p_path))
    cfg = VerificationConfig()
    for seed in range(5):  # USAC samples at random: the verdict must not depend on the draw
        cv2.setRNGSeed(seed)
        g = verify_pair(fq.keypoints, np.full(len(fq), NO_WORD), fq.descriptors, fq.image_shape,
                        fp.keypoints, np.full(len(fp), NO_WORD), fp.descriptors, fp.image_shape, cfg,
                        bruteforce=True, distance=kind.distance,
                        radius=independence_radius(kind.window_radius(fq.sizes), cfg))
        assert not g.verified, (seed, g.model, g.inliers, g.nfa)
