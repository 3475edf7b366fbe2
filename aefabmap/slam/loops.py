"""Loop-closure edges from aefabmap's verified loops: relative pose by PnP on the verified matches.

The detector (runtime/core/detector.py) verifies a loop with a two-view model (H, F or E) and
keeps the inlier point pairs (VerificationConfig.keep_inlier_points). With depth, the place
frame's inlier points become 3-D points in its camera; PnP RANSAC (odometry.pnp_pose) on the
query frame's inlier pixels gives T_query_place, hence the edge T_place_query with metric scale,
which a two-view model alone cannot give. On texture-poor frames a verified loop may rest on
6-10 inliers: that PnP then only seeds guided matching between the two frames' odometry
features (odometry.guided_pose, same settings as the odometry), and the edge is the PnP on those
matches, kept when it has the odometry's min_inliers.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from aefabmap.runtime.core.messages import FrameResult
from aefabmap.slam.odometry import (
    FrameFeatures,
    OdometryConfig,
    backproject,
    guided_pose,
    pnp_pose,
)
from aefabmap.slam.poses import invert


@dataclass
class LoopEdge:
    """A verified loop query -> place with its metric relative pose.

    T_place_query: 4x4, the query camera in the place camera's frame (None: PnP failed);
    verified_inliers / model / nfa: the detector's verification; seed_inliers: PnP inliers among
    the verified matches; pnp_inliers: inliers of the final (guided) PnP.
    """

    query: int
    place: int
    T_place_query: np.ndarray | None
    verified_inliers: int
    model: str | None
    nfa: float | None
    seed_inliers: int = 0
    pnp_inliers: int = 0


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
    if seed.T is None:
        return edge
    rel = guided_pose(query, place, seed.T, K, config)
    edge.pnp_inliers = rel.inliers
    if rel.T is not None:
        edge.T_place_query = invert(rel.T)
    return edge
