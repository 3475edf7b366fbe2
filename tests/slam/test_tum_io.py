"""TUM folders and trajectories: reading, pairing by time, writing (no gtsam/evo needed)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from aefabmap_runtime.errors import DataNotFoundError, InputError
from aefabmap.slam.poses import (
    invert,
    make_pose,
    matrix_to_quaternion,
    pose_difference,
    quaternion_to_matrix,
)
from aefabmap.slam.tum_io import (
    associate,
    read_rgbd_folder,
    read_tum_trajectory,
    write_tum_trajectory,
)


def _random_poses(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        R, _ = cv2.Rodrigues(rng.uniform(-np.pi, np.pi, 3) * [1, 1, 0.99])
        out.append(make_pose(R, rng.uniform(-5, 5, 3)))
    return np.stack(out)


def test_quaternions_round_trip_at_any_angle():
    for T in _random_poses(200):
        q = matrix_to_quaternion(T[:3, :3])
        assert q[3] >= 0 and abs(np.linalg.norm(q) - 1) < 1e-12
        assert np.allclose(quaternion_to_matrix(q), T[:3, :3], atol=1e-12)
    half_turn = np.diag([1.0, -1.0, -1.0])  # 180 degrees about x: the trace is -1
    assert np.allclose(quaternion_to_matrix(matrix_to_quaternion(half_turn)), half_turn)


def test_trajectory_round_trip(tmp_path):
    poses = _random_poses(30, seed=1)
    stamps = 1341841278.8427 + 0.67 * np.arange(30)
    write_tum_trajectory(tmp_path / "t.txt", stamps, poses)
    s2, p2 = read_tum_trajectory(tmp_path / "t.txt")
    assert np.allclose(s2, stamps, atol=1e-6)
    errs = np.array([pose_difference(a, b) for a, b in zip(p2, poses)])
    assert errs[:, 0].max() < 1e-5 and errs[:, 1].max() < 1e-3
    assert np.allclose(invert(poses[3]) @ poses[3], np.eye(4))


def test_association_pairs_closest_stamps_once_within_the_limit():
    a = np.array([0.0, 1.0, 2.0, 3.0])
    b = np.array([0.005, 1.001, 1.012, 2.5, 3.019])
    assert associate(a, b) == [(0, 0), (1, 1), (3, 4)]


def _folder(tmp_path, camera=True, associations=False):
    (tmp_path / "rgb").mkdir()
    (tmp_path / "depth").mkdir()
    rgb, dep = ["# color"], ["# depth"]
    for i in range(3):
        cv2.imwrite(str(tmp_path / "rgb" / f"{i}.png"), np.full((48, 64), 40 * i, np.uint8))
        cv2.imwrite(str(tmp_path / "depth" / f"{i}.png"), np.full((48, 64), 5000 * (i + 1), np.uint16))
        rgb.append(f"{10 + i:.4f} rgb/{i}.png")
        dep.append(f"{10 + i + 0.01:.4f} depth/{i}.png")
    (tmp_path / "rgb.txt").write_text("\n".join(rgb) + "\n")
    (tmp_path / "depth.txt").write_text("\n".join(dep) + "\n")
    if associations:
        (tmp_path / "associations.txt").write_text("".join(
            f"{10 + i:.4f} rgb/{i}.png {10 + i:.4f} depth/{i}.png\n" for i in (2, 0)))
    if camera:
        (tmp_path / "camera.yaml").write_text("fx: 500.0\nfy: 501.0\ncx: 32\ncy: 24\ndistortion: [0, 0]\n")
    write_tum_trajectory(tmp_path / "groundtruth.txt", np.array([10.0, 11.0]), _random_poses(2))
    return tmp_path


def test_rgbd_folder_pairs_rgb_with_depth_and_ground_truth(tmp_path):
    seq = read_rgbd_folder(_folder(tmp_path))
    assert len(seq) == 3 and seq.camera == (500.0, 501.0, 32.0, 24.0)
    assert np.allclose(seq.stamps, [10, 11, 12])
    assert seq.depth_m(1)[0, 0] == pytest.approx(2.0) and seq.gray(2)[0, 0] == 80
    assert np.isfinite(seq.groundtruth[:2]).all() and np.isnan(seq.groundtruth[2]).all()
    assert np.allclose(seq.K, [[500, 0, 32], [0, 501, 24], [0, 0, 1]])


def test_associations_file_wins_and_frames_are_sorted(tmp_path):
    seq = read_rgbd_folder(_folder(tmp_path, associations=True), camera=(1.0, 1.0, 0.0, 0.0))
    assert len(seq) == 2 and np.allclose(seq.stamps, [10, 12]) and seq.camera == (1.0, 1.0, 0.0, 0.0)


def test_missing_pieces_are_named(tmp_path):
    with pytest.raises(DataNotFoundError):
        read_rgbd_folder(tmp_path / "nowhere")
    with pytest.raises(InputError, match="camera"):
        read_rgbd_folder(_folder(tmp_path, camera=False))
