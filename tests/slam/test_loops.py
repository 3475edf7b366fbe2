"""Loop edges from FAB-MAP proposals checked in 3-D: a true revisit gives its metric pose, an
aliased proposal (same descriptors, another 3-D layout) gives none."""

from __future__ import annotations

import numpy as np

from aefabmap.slam.loops import proposal_edge
from aefabmap.slam.odometry import FrameFeatures, OdometryConfig
from aefabmap.slam.poses import invert, make_pose, pose_difference
from tests.slam.test_odometry import K, _scene, _view

CONFIG = OdometryConfig()


def _rot_y(deg: float) -> np.ndarray:
    a = np.deg2rad(deg)
    return np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])


def _edge(query: FrameFeatures, place: FrameFeatures):
    return proposal_edge(40, 3, query, place, K, CONFIG, max_log10_nfa=-4.0, duplicate_radius=3.0)


def test_a_revisit_proposal_gets_its_metric_pose():
    pts, desc = _scene(seed=1)
    T_w_place = np.eye(4)
    T_w_query = make_pose(_rot_y(8.0), np.array([0.3, 0.0, 0.1]))
    edge = _edge(_view(pts, desc, T_w_query), _view(pts, desc, T_w_place))
    assert edge.source == "proposal" and edge.model == "P" and edge.nfa < -4.0
    assert edge.T_place_query is not None and edge.pnp_inliers >= CONFIG.min_inliers
    dt, dr = pose_difference(edge.T_place_query, invert(T_w_place) @ T_w_query)
    assert dt < 0.01 and dr < 0.5


def test_an_aliased_proposal_gets_no_edge():
    """The place shows the query's descriptors on another structure (a look-alike face): matches
    exist, but no camera pose puts the place's 3-D points where the query sees them."""
    pts, desc = _scene(seed=2)
    query = _view(pts, desc, np.eye(4))
    other = np.random.default_rng(3).permutation(pts.shape[0])
    place = _view(pts[other], desc, np.eye(4))  # same descriptors, shuffled positions
    edge = _edge(query, place)
    assert edge.T_place_query is None
    assert edge.nfa is None or edge.nfa >= -4.0


def test_frames_without_features_give_no_edge():
    empty = FrameFeatures(np.zeros((0, 2), np.float32), np.zeros((0, 32), np.uint8), np.zeros((480, 640), np.float32))
    pts, desc = _scene(seed=4)
    edge = _edge(empty, _view(pts, desc, np.eye(4)))
    assert edge.T_place_query is None and edge.pnp_inliers == 0


def test_the_significance_bar_decides():
    """The same revisit, asked for an impossible significance, gives no edge: the a-contrario
    test, not the PnP alone, admits a proposal."""
    pts, desc = _scene(seed=1)
    query = _view(pts, desc, make_pose(_rot_y(8.0), np.array([0.3, 0.0, 0.1])))
    edge = proposal_edge(40, 3, query, _view(pts, desc, np.eye(4)), K, CONFIG, max_log10_nfa=-1e6, duplicate_radius=3.0)
    assert edge.T_place_query is None and edge.nfa is not None and edge.nfa > -1e6
