"""ATE / RPE through evo: a rigidly moved copy scores zero, known noise scores what it should."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from aefabmap.slam.poses import make_pose

pytest.importorskip("evo")

from aefabmap.slam.metrics import trajectory_errors


def _trajectory(n=40, seed=0):
    rng = np.random.default_rng(seed)
    poses, T = [], np.eye(4)
    for _ in range(n):
        R, _ = cv2.Rodrigues(rng.normal(0, 0.05, 3))
        T = T @ make_pose(R, rng.normal(0, 0.1, 3))
        poses.append(T)
    return np.arange(n) * 0.5, np.stack(poses)


def test_a_rigidly_moved_copy_has_no_error_after_alignment():
    stamps, gt = _trajectory()
    R, _ = cv2.Rodrigues(np.array([0.3, -1.0, 2.0]))
    moved = np.stack([make_pose(R, [1.0, 2.0, 3.0]) @ T for T in gt])
    e = trajectory_errors(stamps, moved, stamps, gt)
    assert e.ate_rmse_m < 1e-9 and e.rpe_trans_rmse_m < 1e-9 and e.rpe_rot_rmse_deg < 1e-6 and e.pairs == 40


def test_position_noise_shows_in_the_ate():
    stamps, gt = _trajectory()
    noisy = gt.copy()
    noisy[:, :3, 3] += np.random.default_rng(1).normal(0, 0.05, (40, 3))
    e = trajectory_errors(stamps, noisy, stamps, gt)
    assert 0.05 < e.ate_rmse_m < 0.11  # sqrt(3) * 0.05 = 0.087 before alignment absorbs a little
    assert e.rpe_trans_rmse_m > e.ate_rmse_m  # consecutive differences double the variance
