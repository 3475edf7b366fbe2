"""`aefabmap slam` end to end: the TUM cabinet subsample (skipped without the data) and a small synthetic folder."""

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


def _textured_rgbd_folder(root, frames: int = 6):
    """A TUM folder of `frames` views of one random texture sliding 4 px a frame, depth 2 m everywhere."""
    import cv2

    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    rng = np.random.default_rng(0)
    texture = cv2.GaussianBlur(rng.integers(0, 256, (480 + 4 * frames, 640 + 4 * frames), dtype=np.uint8), (3, 3), 0)
    lines = []
    for i in range(frames):
        cv2.imwrite(str(root / f"rgb/{i}.png"), texture[4 * i:4 * i + 480, 4 * i:4 * i + 640])
        cv2.imwrite(str(root / f"depth/{i}.png"), np.full((480, 640), 10000, np.uint16))  # TUM scale: 5000 per metre
        lines.append(f"{i * 0.5:.3f} rgb/{i}.png {i * 0.5:.3f} depth/{i}.png")
    (root / "associations.txt").write_text("\n".join(lines) + "\n")
    (root / "camera.yaml").write_text("fx: 500\nfy: 500\ncx: 320\ncy: 240\n")
    return root


@pytest.mark.parametrize("quiet", [False, True], ids=["progress", "no-progress"])
def test_slam_shows_progress_bars_unless_told_not_to(tmp_path, quiet):
    import subprocess
    import sys

    from aefabmap.cli.options import default_bundle

    rgbd = _textured_rgbd_folder(tmp_path / "rgbd")
    out = subprocess.run([sys.executable, "-m", "aefabmap.cli.main", "slam", "--rgbd", str(rgbd), "--model",
                          str(default_bundle()), "--out", str(tmp_path / "out"), "--no-plot",
                          *(["--no-progress"] if quiet else [])], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout)["frames"] == 6  # the JSON summary on stdout, bars only on stderr
    bars = [line for line in out.stderr.replace("\r", "\n").splitlines() if line.startswith(("frames:", "loop edges:"))]
    if quiet:
        assert bars == [], out.stderr
    else:
        assert any("6/6" in b for b in bars if b.startswith("frames:")), out.stderr
        assert any("6/6" in b for b in bars if b.startswith("loop edges:")), out.stderr
