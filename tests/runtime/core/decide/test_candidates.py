"""The detector reports its candidates and, on request, the inlier point pairs of each check."""

from __future__ import annotations

import json
from types import SimpleNamespace

import cv2
import numpy as np

from aefabmap_runtime.core.decide.candidates import CandidateConfig
from aefabmap_runtime.core.verify.verification import VerificationConfig
from tests.runtime.core.verify.test_verification import PERSPECTIVE, _detector, texture


def _run(tmp_path, keep: bool):
    det = _detector(tmp_path, verification=VerificationConfig(keep_inlier_points=keep))
    frames = [texture(s) for s in range(40, 45)] + [cv2.warpPerspective(texture(41), PERSPECTIVE, (480, 360))]
    return [det.process(f) for f in frames]


def test_candidates_rank_places_and_mark_the_checked_ones(tmp_path):
    results = _run(tmp_path, keep=False)
    assert results[0].candidates == []  # empty map
    r = results[-1]
    assert r.verified and r.verified_frame == 1
    ranks = [c.rank for c in r.candidates if c.source in (None, "fabmap")]
    assert ranks == sorted(ranks) and len(r.candidates) <= CandidateConfig().top_k + r.candidates_tried
    llrs = [c.llr for c in r.candidates]
    assert llrs == sorted(llrs, reverse=True) and r.candidates[0].llr == r.llr
    chosen = [c for c in r.candidates if c.verified]
    assert len(chosen) == 1 and chosen[0].frame == 1 and chosen[0].checked and chosen[0].inliers == r.inliers
    assert sum(c.checked for c in r.candidates) == r.candidates_tried
    assert chosen[0].inlier_points is None  # not kept unless asked
    json.dumps(r.to_dict())  # still a JSON-able message


def test_inlier_points_on_request_fit_the_accepted_geometry(tmp_path):
    r = _run(tmp_path, keep=True)[-1]
    c = next(c for c in r.candidates if c.verified)
    pts = np.asarray(c.inlier_points, np.float32)  # JSON-able lists in the result
    assert pts.shape == (r.inliers, 4) and pts.dtype == np.float32
    # Place points map onto query points: by the homography (H) or onto their epipolar line (F).
    G = np.asarray(r.geometry)
    hp = np.c_[pts[:, 2:], np.ones(len(pts))]
    if r.geometry_model == "H":
        proj = hp @ G.T
        err = np.linalg.norm(proj[:, :2] / proj[:, 2:] - pts[:, :2], axis=1)
    else:
        lines = hp @ G.T
        err = np.abs(np.sum(np.c_[pts[:, :2], np.ones(len(pts))] * lines, axis=1)) / np.hypot(lines[:, 0], lines[:, 1])
    assert np.median(err) < 5.0


#: Pinhole intrinsics (fx, fy, cx, cy) of `calibrated_scene`'s camera, as `--camera` gives them.
CAMERA = (400.0, 400.0, 320.0, 240.0)


def calibrated_scene(seed: int = 2) -> SimpleNamespace:
    """One 3-D point cloud (not planar: the essential matrix wins) seen by the CAMERA: `frame(points)`
    gives its keypoints (Features) from `points`; the place sees `points`, the query `query` (the
    camera turned by `rotation` and moved to `centre`); `rng` goes on drawing after the scene."""
    from aefabmap_runtime.core.features.features import Features

    rng = np.random.default_rng(seed)
    n = 300
    points = np.c_[rng.uniform(-4, 4, n), rng.uniform(-3, 3, n), rng.uniform(5, 25, n)]
    desc = rng.integers(0, 256, (n, 32), dtype=np.uint8)
    fx, fy, cx, cy = CAMERA
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    rotation, _ = cv2.Rodrigues(np.array([0.02, 0.25, 0.0]))
    centre = np.array([1.2, 0.0, 0.4])

    def frame(pts, d=desc):
        x = pts @ K.T
        return Features((x[:, :2] / x[:, 2:]).astype(np.float32), np.full(n, 31, np.float32), d, (480, 640))

    return SimpleNamespace(rng=rng, n=n, points=points, descriptors=desc, rotation=rotation, centre=centre,
                           query=(points - centre) @ rotation, frame=frame)


def test_a_calibrated_verified_loop_carries_the_query_pose_relative_to_the_place(tmp_path):
    """Two frames of `calibrated_scene`, fed as keypoints: the result's relative_rotation /
    relative_translation are the query camera's pose in the place frame."""
    scene = calibrated_scene()
    n, rng, frame, X, R_pq, centre = scene.n, scene.rng, scene.frame, scene.points, scene.rotation, scene.centre

    # min_inliers_h=1000: no homography, the epipolar model decides (exclude 2: the third frame sees the first).
    det = _detector(tmp_path, verification=VerificationConfig(camera=CAMERA, min_inliers_h=1000))
    words = np.arange(n) % det.bundle.vocabulary_size
    det.process_words(words, features=frame(X))
    other = det.process_words(words, features=frame(X, rng.integers(0, 256, (n, 32), dtype=np.uint8)))
    assert other.relative_rotation is None  # nothing verified
    r = det.process_words(words, features=frame(scene.query))
    assert r.verified and r.verified_frame == 0 and r.geometry_model == "E"
    R = np.asarray(r.relative_rotation)
    assert np.degrees(np.arccos(np.clip((np.trace(R.T @ R_pq) - 1) / 2, -1, 1))) < 0.5
    t = np.asarray(r.relative_translation)
    assert np.allclose(t, centre / np.linalg.norm(centre), atol=0.01)
    assert json.loads(r.to_json_bytes())["relative_translation"] == r.relative_translation
