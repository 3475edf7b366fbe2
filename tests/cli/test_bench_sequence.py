"""Plumbing of `aefabmap bench sequence` (a tiny generated folder; no timing asserts)."""

from __future__ import annotations

import json

import pytest

from aefabmap.cli.main import main


@pytest.mark.timeout(180)
def test_bench_sequence_runs_the_frame_loop_over_a_folder(tmp_path, capsys):
    from aefabmap_runtime.tools.synthetic_route import make_demo_sequence

    make_demo_sequence(tmp_path / "seq", n_frames=12, seed=3, size=(320, 240))
    out = tmp_path / "sequence.json"
    code = main(["bench", "sequence", "--images", str(tmp_path / "seq"), "--exclude", "2", "--json", str(out)])
    assert code == 0
    doc = json.loads(out.read_text())
    assert doc["benchmark"] == "sequence" and doc["frames"] == 12 and doc["image_size_wh"] == [320, 240]
    assert doc["single_core"] is True and doc["threads_env"]["OMP_NUM_THREADS"] == "1"
    for stage in ("decode", "features", "quantise", "inference", "verification"):
        assert doc["stages_ms"][stage]["n"] == 12 and doc["stages_cpu_ms"][stage]["median"] >= 0
    assert 0 < doc["total_ms"]["median"] <= doc["total_ms"]["max"]
    assert doc["places"] == 12 - 2  # delayed insertion keeps the last `exclude` frames pending
    assert "frames per second" in capsys.readouterr().out


def test_bench_sequence_refuses_a_missing_folder_in_one_line(tmp_path, caplog):
    code = main(["bench", "sequence", "--images", str(tmp_path / "nowhere")])
    assert code == 4
    assert any("does not exist" in r.getMessage() for r in caplog.records)


@pytest.mark.timeout(180)
def test_bench_sequence_calls_attributes_time_to_the_libraries(tmp_path, capsys):
    from aefabmap_runtime.tools.call_profile import GROUPS
    from aefabmap_runtime.tools.synthetic_route import make_demo_sequence

    make_demo_sequence(tmp_path / "seq", n_frames=10, seed=4, size=(320, 240))
    out = tmp_path / "sequence.json"
    code = main(["bench", "sequence", "--images", str(tmp_path / "seq"), "--exclude", "2", "--calls",
                 "--json", str(out)])
    assert code == 0
    calls = json.loads(out.read_text())["calls_cpu_ms_per_frame"]
    assert set(calls) == {*GROUPS, "rest"}
    assert all(calls[g] >= 0 for g in GROUPS)
    # Every frame is decoded and resized by OpenCV, its ORB keypoints detected and described by the
    # compiled kernels (by OpenCV where they are not built), its words found by onnxruntime's product.
    assert calls["opencv_features"] + calls["native_kernels"] > 0
    assert calls["opencv_image"] > 0 and calls["onnxruntime"] > 0
    from aefabmap_runtime.core.kernels import native
    if native.available():
        assert calls["opencv_features"] == 0 and calls["native_kernels"] > 0
    assert "inside: opencv_features" in capsys.readouterr().out


@pytest.mark.timeout(180)
def test_bench_sequence_runs_with_run_s_verification_options(tmp_path):
    from aefabmap_runtime.tools.synthetic_route import make_demo_sequence

    make_demo_sequence(tmp_path / "seq", n_frames=8, seed=5, size=(320, 240))
    out = tmp_path / "sequence.json"
    code = main(["bench", "sequence", "--images", str(tmp_path / "seq"), "--exclude", "2", "--verify-keypoints", "300",
                 "--verify-bruteforce", "1", "--no-verify-upright", "--json", str(out)])
    assert code == 0
    doc = json.loads(out.read_text())
    assert (doc["verify_keypoints"], doc["verify_bruteforce"], doc["verify_upright"]) == (300, 1, False)


@pytest.mark.parametrize("option", [["--verify-keypoints", "0"], ["--verify-bruteforce", "-1"], ["--exclude", "-1"]])
def test_bench_sequence_refuses_bad_settings_in_one_line_before_loading(tmp_path, caplog, option):
    code = main(["bench", "sequence", "--images", str(tmp_path), *option])
    assert code == 2
    assert len([r for r in caplog.records if r.levelname == "ERROR"]) == 1


@pytest.mark.timeout(180)
def test_bench_sequence_workers_reports_both_thread_counts(tmp_path, capsys):
    from aefabmap_runtime.tools.synthetic_route import make_demo_sequence

    make_demo_sequence(tmp_path / "seq", n_frames=12, seed=6, size=(320, 240))
    out = tmp_path / "sequence.json"
    code = main(["bench", "sequence", "--images", str(tmp_path / "seq"), "--exclude", "2", "--workers", "2",
                 "--json", str(out)])
    assert code == 0
    doc = json.loads(out.read_text())
    one, two = doc["workers"]["1"], doc["workers"]["2"]
    for run in (one, two):
        assert run["cpu_ms_per_frame"] > 0 and run["frames_per_second"] > 0 and run["wall_s"] > 0
        assert set(run["stages_ms_mean"]) == {"decode", "features", "quantise", "inference", "verification"}
    assert one["loops"] == two["loops"] == doc["loops"] and one["cores"] == 1
    assert "workers" in capsys.readouterr().out


def test_bench_sequence_refuses_a_bad_worker_count(tmp_path, caplog):
    code = main(["bench", "sequence", "--images", str(tmp_path), "--workers", "0"])
    assert code != 0
    assert any("workers" in r.getMessage() for r in caplog.records)
