"""Pose graph (gtsam): a loop edge removes odometry drift; a wrong one is muted by the robust kernel."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from aefabmap_runtime.errors import ConfigError
from aefabmap.slam.poses import invert, make_pose, pose_difference

pytest.importorskip("gtsam")

from aefabmap.slam.pose_graph import Edge, PoseGraphConfig, optimize


def _rot_z(deg: float) -> np.ndarray:
    R, _ = cv2.Rodrigues(np.array([0.0, 0.0, np.radians(deg)]))
    return R


def _circle(n: int = 24, radius: float = 2.0) -> np.ndarray:
    """n camera-to-world poses around a circle, the last one back at the first."""
    out = []
    for k in range(n + 1):
        a = 2 * np.pi * k / n
        out.append(make_pose(_rot_z(np.degrees(a)), [radius * np.cos(a), radius * np.sin(a), 0.0]))
    return np.stack(out[:-1])


def _odometry(truth: np.ndarray, bias_deg: float) -> tuple[np.ndarray, list[Edge]]:
    """Dead reckoning with a yaw bias per step (drift), and its edges."""
    poses, edges = [truth[0]], []
    for k in range(1, len(truth)):
        step = invert(truth[k - 1]) @ truth[k]
        step = make_pose(_rot_z(bias_deg) @ step[:3, :3], step[:3, 3])
        edges.append(Edge(k - 1, k, step, 0.02, 0.03))
        poses.append(poses[-1] @ step)
    return np.stack(poses), edges


def test_a_loop_edge_removes_the_drift():
    truth = _circle()
    init, edges = _odometry(truth, bias_deg=0.5)  # 0.4 m, 11.5 degrees of drift
    drift = pose_difference(init[-1], truth[-1])[0]
    loop = Edge(0, len(truth) - 1, invert(truth[0]) @ truth[-1], 0.02, 0.03, loop=True)
    res = optimize(init, edges + [loop])
    after = max(pose_difference(a, b)[0] for a, b in zip(res.poses, truth))
    assert drift > 0.3 and after < 0.1 * drift, (drift, after)
    assert res.final_error < res.initial_error and res.loop_weights[0] > 0.5
    assert np.allclose(res.poses[0], init[0], atol=1e-9)  # frame 0 fixed


def test_the_robust_kernel_mutes_a_wrong_loop_edge():
    truth = _circle()
    init, edges = _odometry(truth, bias_deg=0.5)
    good = Edge(0, len(truth) - 1, invert(truth[0]) @ truth[-1], 0.02, 0.03, loop=True)
    # A perceptual alias: frame 12 (the far side) claimed to be 0.3 m from frame 0.
    wrong = Edge(0, 12, make_pose(np.eye(3), [0.3, 0.0, 0.0]), 0.02, 0.03, loop=True)
    robust = optimize(init, edges + [good, wrong], PoseGraphConfig(kernel="cauchy"))
    plain = optimize(init, edges + [good, wrong], PoseGraphConfig(kernel="none"))
    err = lambda r: max(pose_difference(a, b)[0] for a, b in zip(r.poses, truth))
    assert err(robust) < 0.05 and err(plain) > 1.0, (err(robust), err(plain))
    assert robust.loop_weights[1] < 0.05 and robust.loop_weights[0] > 0.9


def test_bad_edges_and_settings_are_refused():
    with pytest.raises(ConfigError):
        PoseGraphConfig(kernel="tukey")
    with pytest.raises(ConfigError):
        optimize(np.stack([np.eye(4)] * 2), [Edge(0, 5, np.eye(4), 0.1, 0.1)])
