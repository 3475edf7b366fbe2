"""Localization metrics (runtime/aefabmap_runtime/tools/localize_eval.py): a map built over the first
lap, the second lap localized against it read-only, scored on the cut ground truth."""

from __future__ import annotations

import pytest

from aefabmap_runtime.adapters.bundle_reader import load_detector
from aefabmap_runtime.adapters.state_dir import MapStateDir, bundle_id
from aefabmap_runtime.core.detector import DetectorConfig
from aefabmap_runtime.errors import ConfigError
from aefabmap_runtime.tools.localize_eval import localize_sequence, state_digest
from aefabmap_runtime.tools.synthetic_route import generate_loop_sequence, write_sequence

N, HALF = 40, 20


@pytest.fixture(scope="module")
def lap(tmp_path_factory):
    from aefabmap.cli.demo import default_bundle

    tmp = tmp_path_factory.mktemp("lap")
    images, gt = generate_loop_sequence(N, seed=3, size=(640, 480))
    write_sequence(tmp / "seq", images, gt)
    det = load_detector(default_bundle(), DetectorConfig(exclude=1))
    for im in images[:HALF]:
        det.process(im, 0)
    with MapStateDir(tmp / "state", bundle_id(det.manifest)) as d:
        d.save(det.state())
    return default_bundle(), tmp


def test_the_second_lap_localizes_against_the_first_and_the_state_is_not_written(lap):
    bundle, tmp = lap
    before = state_digest(tmp / "state")
    metrics, run = localize_sequence(bundle, tmp / "seq", tmp / "seq" / "gt.npy", tmp / "state",
                                     DetectorConfig(exclude=1), show_progress=False)
    assert run.first == HALF and metrics["queries"] == N - HALF and metrics["map_frames"] == HALF
    assert len(run.run.results) == N - HALF
    _, gt = generate_loop_sequence(N, seed=3, size=(640, 480))
    v = metrics["verified"]
    # only queries whose true place is a map frame count, and only map frames can be answers
    assert v["relevant_frames"] == int(gt[HALF:, :HALF].any(axis=1).sum()) > 0 and v["predictions"] > 0
    assert all(r.verified_frame < HALF for r in run.run.results if r.verified)
    # only the map's last frame, still queued when it was saved, enters, once its delay has passed
    assert [(r.sequence, r.inserted_frame) for r in run.run.results if r.inserted_frame is not None] == [
        (HALF, HALF - 1)]
    assert state_digest(tmp / "state") == before


def test_a_map_built_over_the_whole_sequence_leaves_nothing_to_localize(lap, tmp_path):
    bundle, tmp = lap
    images, gt = generate_loop_sequence(HALF, seed=3, size=(640, 480))
    write_sequence(tmp_path / "short", images[:HALF], gt[:HALF, :HALF])
    with pytest.raises(ConfigError, match="no frame is left"):
        localize_sequence(bundle, tmp_path / "short", tmp_path / "short" / "gt.npy", tmp / "state",
                          DetectorConfig(exclude=1), show_progress=False)


def test_eval_localize_prints_the_metrics_and_writes_json(lap, tmp_path):
    import json
    import subprocess
    import sys

    bundle, tmp = lap
    before = state_digest(tmp / "state")
    out = subprocess.run([sys.executable, "-m", "aefabmap.cli.main", "eval", "--model", str(bundle), "--images",
                          str(tmp / "seq"), "--gt", str(tmp / "seq" / "gt.npy"), "--state", str(tmp / "state"),
                          "--localize", "--exclude", "1", "--no-progress", "--json", str(tmp_path / "m.json")],
                         capture_output=True, text=True, timeout=300, check=False)
    assert out.returncode == 0, out.stderr
    assert f"localized frames {HALF}-{N - 1}" in out.stdout
    metrics = json.loads((tmp_path / "m.json").read_text())
    assert metrics["queries"] == N - HALF and metrics["verified"]["predictions"] > 0
    assert state_digest(tmp / "state") == before
    both = subprocess.run([sys.executable, "-m", "aefabmap.cli.main", "eval", "--model", str(bundle), "--images",
                           str(tmp / "seq"), "--gt", str(tmp / "seq" / "gt.npy"), "--localize"],
                          capture_output=True, text=True, timeout=300, check=False)
    assert both.returncode == 2 and "--localize needs --state" in both.stderr
