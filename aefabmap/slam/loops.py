"""Loop-closure edges from aefabmap's verified loops: relative pose by PnP on the verified matches.

The detector (runtime/aefabmap_runtime/core/detector.py) verifies a loop with a two-view model (H, F or E) and
keeps the inlier point pairs (VerificationConfig.keep_inlier_points). With depth, the place
frame's inlier points become 3-D points in its camera; PnP RANSAC (odometry.pnp_pose) on the
query frame's inlier pixels gives T_query_place, hence the edge T_place_query with metric scale,
which a two-view model alone cannot give. On texture-poor frames a verified loop may rest on a
handful of inliers (docs/slam.md, "Results: TUM fr3 cabinet, 58-frame subsample"): that PnP
then only seeds guided matching between the two frames' odometry features (odometry.guided_pose,
same settings as the odometry), and the edge is the PnP on those matches, kept when it has the
odometry's min_inliers.

A frame the two-view test verified nothing for may still hold a revisit: on texture-poor frames
the detector's few keypoints (docs/results.md, "SLAM") leave too few independent matches for it.
`proposal_edge` checks such a frame against the detector's FAB-MAP candidates in 3-D instead, as
ORB-SLAM checks its bag-of-words candidates: the two frames' odometry features (4000 per frame)
are matched, the place's depth gives 3-D points, and a PnP pose is kept only when its inliers are
very unlikely by chance (the same a-contrario test and bar as the two-view models, `acontrario.py`
model "P": reprojection errors in the query image). It then goes through the same guided matching
and inlier floor as a verified loop.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from aefabmap_runtime.core.verify.acontrario import match_region, significance
from aefabmap_runtime.core.records.messages import FrameResult
from aefabmap_runtime.core.verify.verification import distinct_matches
from aefabmap.slam.odometry import (
    FrameFeatures,
    OdometryConfig,
    backproject,
    camera_points,
    guided_pose,
    match_orb,
    pnp_pose,
    to_pixels,
)
from aefabmap.slam.poses import invert


@dataclass
class LoopEdge:
    """A verified loop query -> place with its metric relative pose.

    T_place_query: 4x4, the query camera in the place camera's frame (None: PnP failed);
    verified_inliers / model / nfa: the detector's verification (source "verified") or the 3-D
    check of a proposal (source "proposal": model "P", its PnP inliers and log10 NFA);
    seed_inliers: PnP inliers among those matches; pnp_inliers: inliers of the final (guided) PnP.
    """

    query: int
    place: int
    T_place_query: np.ndarray | None
    verified_inliers: int
    model: str | None
    nfa: float | None
    seed_inliers: int = 0
    pnp_inliers: int = 0
    source: str = "verified"


def exclusion_frames(stamps: np.ndarray, min_gap_s: float) -> int:
    """Frames a loop must be apart: min_gap_s in frames at the sequence's median frame interval (>= 1)."""
    dt = float(np.median(np.diff(stamps))) if stamps.size > 1 else 1.0
    return max(1, math.ceil(min_gap_s / max(dt, 1e-6) - 1e-9))


def verified_matches(result: FrameResult) -> tuple[np.ndarray, np.ndarray] | None:
    """(query pixels (K, 2), place pixels (K, 2)) of the verified candidate's inliers, or None.

    Needs a detector run with VerificationConfig.keep_inlier_points.
    """
    if not result.verified:
        return None
    for cand in result.candidates:
        if cand.verified and cand.place == result.verified_place and cand.inlier_points:
            pts = np.asarray(cand.inlier_points, np.float64)
            return pts[:, :2], pts[:, 2:4]
    return None


#: Fewest verified matches PnP may seed from: EPnP's 5-point minimal sample plus one check.
MIN_SEED_INLIERS = 6


def loop_edge(result: FrameResult, query: FrameFeatures, place: FrameFeatures, K: np.ndarray,
              config: OdometryConfig) -> LoopEdge | None:
    """The edge of one verified result (None when it is not a verified loop with inlier points).

    query / place: the two frames' odometry features with depth (place.depth gives the 3-D points).
    """
    matches = verified_matches(result)
    if matches is None:
        return None
    xq, xp = matches
    edge = LoopEdge(result.sequence, int(result.verified_frame), None, int(result.inliers), result.geometry_model,
                    result.nfa)
    pts, ok = backproject(xp, place.depth, K, config.min_depth, config.max_depth)
    seed = pnp_pose(pts, xq[ok], K, dataclasses.replace(config, min_inliers=MIN_SEED_INLIERS))  # T_query_place
    edge.seed_inliers = seed.inliers
    return _refined(edge, seed.T, query, place, K, config)


def _refined(edge: LoopEdge, seed_T: np.ndarray | None, query: FrameFeatures, place: FrameFeatures, K: np.ndarray,
             config: OdometryConfig) -> LoopEdge:
    """The edge's pose by guided matching from a seed T_query_place (none without a seed)."""
    if seed_T is None:
        return edge
    rel = guided_pose(query, place, seed_T, K, config)
    edge.pnp_inliers = rel.inliers
    if rel.T is not None:
        edge.T_place_query = invert(rel.T)
    return edge


def proposal_edge(query_index: int, place_index: int, query: FrameFeatures, place: FrameFeatures, K: np.ndarray,
                  config: OdometryConfig, max_log10_nfa: float, duplicate_radius: float) -> LoopEdge:
    """A FAB-MAP proposal query -> place checked in 3-D (see the module docstring).

    Matches the two frames' odometry features (`match_orb`), keeps one match per location
    (`distinct_matches`, duplicate_radius pixels: copies of a corner are not independent
    evidence), seeds a pose by PnP on the place's 3-D points, and accepts it when the log10 NFA of
    its reprojection errors (region: the box of the query's matched points, floored at 1/8 of
    the image's long side, as the two-view test does) is below max_log10_nfa. The edge is then
    the guided PnP of `loop_edge`. Returns the edge; T_place_query is None when it failed.
    """
    edge = LoopEdge(query_index, place_index, None, 0, "P", None, source="proposal")
    pairs = match_orb(query.desc, place.desc, config.ratio, config.max_hamming)
    if pairs.shape[0] == 0:
        return edge
    pts, ok = backproject(place.xy[pairs[:, 1]], place.depth, K, config.min_depth, config.max_depth)
    xq = query.xy[pairs[ok, 0]].astype(np.float64)
    xp = place.xy[pairs[ok, 1]].astype(np.float64)
    keep = distinct_matches(xq, xp, duplicate_radius, duplicate_radius)
    pts, xq = pts[keep], xq[keep]
    seed = pnp_pose(pts, xq, K, dataclasses.replace(config, min_inliers=MIN_SEED_INLIERS))  # T_query_place
    edge.seed_inliers = seed.inliers
    if seed.T is None:
        return edge
    cam = camera_points(pts, seed.T)
    with np.errstate(divide="ignore", invalid="ignore"):  # points behind the camera: error inf below
        uv = to_pixels(cam, K)
    err = np.where(cam[:, 2] > config.min_depth, np.linalg.norm(uv - xq, axis=1), np.inf)
    w, h = match_region(xq, long_side=float(max(query.depth.shape)))
    sig = significance(err, "P", w, h, config.reprojection_px)
    edge.verified_inliers, edge.nfa = sig.inliers, sig.log10_nfa
    return _refined(edge, seed.T if sig.log10_nfa < max_log10_nfa else None, query, place, K, config)
