"""The detector reports its candidates and, on request, the inlier point pairs of each check."""

from __future__ import annotations

import json

import cv2
import numpy as np

from aefabmap.runtime.core.verification import VerificationConfig
from tests.runtime.core.test_verification import PERSPECTIVE, _detector, texture


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
    assert ranks == sorted(ranks) and len(r.candidates) <= VerificationConfig().top_k + r.candidates_tried
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
