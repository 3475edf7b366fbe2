"""`aefabmap slam` end to end on the TUM cabinet subsample (skipped without the data or the extra)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from aefabmap.cli.main import main
from tests.conftest import data_root

pytest.importorskip("gtsam")
pytest.importorskip("evo")

@pytest.mark.slow
@pytest.mark.data
def test_slam_writes_trajectories_metrics_and_plot(tmp_path):
    from aefabmap.slam.tum_io import read_tum_trajectory

    root = data_root() / "trajectory" / "tum_fr3_cabinet"
    if not (root / "groundtruth.txt").is_file():
        pytest.skip("tum_fr3_cabinet not found")
    from aefabmap.cli.demo import default_bundle

    bundle = default_bundle()  # the shipped ORB bundle: no trained bundle needed in CI
    out = tmp_path / "out"
    assert main(["slam", "--rgbd", str(root), "--model", str(bundle), "--out", str(out)]) == 0
    for name in ("odometry.txt", "optimized.txt", "metrics.json", "trajectory.png"):
        assert (out / name).is_file(), name
    stamps, poses = read_tum_trajectory(out / "optimized.txt")
    assert stamps.size == 58 and np.allclose(poses[0], np.eye(4), atol=1e-5)
    m = json.loads((out / "metrics.json").read_text())
    assert m["odometry"]["ate_rmse_m"] < 0.25 and m["optimized"]["ate_rmse_m"] < 0.25
    assert m["wrong_loop_edges"] == 0 or all(r["kernel_weight"] < 0.1 for r in m["loop_edge_checks"] if r.get("wrong"))
    assert m["exclude_frames"] == 15  # 10 s at ~0.67 s per frame
    from aefabmap_runtime.core.run_config import RunConfig

    run_config = RunConfig.from_dict(m["run_config"])  # the detector's settings, whole and readable back
    assert run_config.detector.exclude == 15 and run_config.detector.verification.camera is not None


def test_slam_without_a_camera_is_refused(tmp_path):
    (tmp_path / "rgb.txt").write_text("0.0 a.png\n1.0 b.png\n")
    (tmp_path / "depth.txt").write_text("0.0 a_d.png\n1.0 b_d.png\n")
    assert main(["slam", "--rgbd", str(tmp_path), "--model", str(tmp_path), "--out", str(tmp_path / "o")]) == 4
