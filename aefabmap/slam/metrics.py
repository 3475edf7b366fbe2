"""Trajectory error against ground truth with evo (as a library): ATE and RPE.

ATE: the estimate is aligned to the ground truth by the rigid (SE(3), no scale: RGB-D is metric)
Umeyama fit of the positions, then the RMSE of the position differences (m). RPE: errors of the
relative motion between consecutive frames (delta = 1 frame), translation (m) and rotation (deg),
RMSE; no alignment needed. Frames are paired by time stamp (max 0.02 s apart).
"""

from __future__ import annotations

import copy
from dataclasses import asdict, dataclass

import numpy as np

from aefabmap_runtime.errors import InputError


@dataclass
class TrajectoryErrors:
    """ate_rmse_m, ate_mean_m, ate_max_m: absolute position error after SE(3) alignment;
    rpe_trans_rmse_m, rpe_rot_rmse_deg: relative pose error per frame step; pairs: frames compared."""

    ate_rmse_m: float
    ate_mean_m: float
    ate_max_m: float
    rpe_trans_rmse_m: float
    rpe_rot_rmse_deg: float
    pairs: int

    def to_dict(self) -> dict:
        return asdict(self)


def _trajectory(stamps: np.ndarray, poses: np.ndarray):
    from evo.core.trajectory import PoseTrajectory3D

    ok = np.all(np.isfinite(poses.reshape(len(poses), -1)), axis=1)
    return PoseTrajectory3D(poses_se3=list(poses[ok]), timestamps=np.asarray(stamps)[ok])


def aligned(stamps: np.ndarray, est: np.ndarray, gt_stamps: np.ndarray, gt: np.ndarray,
            max_dt: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """(est aligned to gt, gt) as (M, 4, 4) arrays of the frames paired by time (SE(3) Umeyama)."""
    from evo.core import sync

    ref, e = sync.associate_trajectories(_trajectory(gt_stamps, gt), _trajectory(stamps, est), max_diff=max_dt)
    e = copy.deepcopy(e)
    e.align(ref, correct_scale=False)
    return np.stack(e.poses_se3), np.stack(ref.poses_se3)


def trajectory_errors(stamps: np.ndarray, est: np.ndarray, gt_stamps: np.ndarray, gt: np.ndarray,
                      max_dt: float = 0.02) -> TrajectoryErrors:
    """ATE and RPE of an estimate ((N,) stamps s, (N, 4, 4) camera-to-world) against the ground truth."""
    from evo.core import metrics, sync

    try:
        ref, e = sync.associate_trajectories(_trajectory(gt_stamps, gt), _trajectory(stamps, est), max_diff=max_dt)
    except sync.SyncException as exc:
        raise InputError(f"trajectory and ground truth share no time stamps: {exc}") from exc
    if ref.num_poses < 3:
        raise InputError(f"only {ref.num_poses} frames pair with the ground truth: no metric")
    e_al = copy.deepcopy(e)
    e_al.align(ref, correct_scale=False)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, e_al))
    stats = ape.get_all_statistics()
    rpe_t = metrics.RPE(metrics.PoseRelation.translation_part, delta=1, delta_unit=metrics.Unit.frames)
    rpe_t.process_data((ref, e))
    rpe_r = metrics.RPE(metrics.PoseRelation.rotation_angle_deg, delta=1, delta_unit=metrics.Unit.frames)
    rpe_r.process_data((ref, e))
    return TrajectoryErrors(
        ate_rmse_m=float(stats["rmse"]), ate_mean_m=float(stats["mean"]), ate_max_m=float(stats["max"]),
        rpe_trans_rmse_m=float(rpe_t.get_statistic(metrics.StatisticsType.rmse)),
        rpe_rot_rmse_deg=float(rpe_r.get_statistic(metrics.StatisticsType.rmse)),
        pairs=int(ref.num_poses),
    )
