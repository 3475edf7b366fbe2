"""`aefabmap run --state DIR` as processes: SIGTERM, restart with the same DIR, and the revisits
after the restart are found against the frames stored before it, with the results of an
uninterrupted run."""

from __future__ import annotations

import subprocess

import numpy as np
import pytest

from aefabmap_runtime.adapters.bundle_reader import load_detector
from aefabmap_runtime.adapters.frame_loop import FrameLoop
from aefabmap_runtime.adapters.replay import NONDETERMINISTIC_FIELDS
from aefabmap_runtime.core.detector import DetectorConfig
from aefabmap_runtime.tools.synthetic_route import (
    generate_loop_sequence,
    write_sequence,
)
from tests.conftest import make_synthetic_bundle

from .stream_fakes import CLI, KEY, run_node_process, session_pair
N, HALF = 120, 60  # two laps: frames 60.. revisit frames 0..59 (run's exclusion window is 50)


def _deterministic(doc: dict) -> dict:
    return {k: v for k, v in doc.items() if k not in NONDETERMINISTIC_FIELDS and k != "stamp_ns"}


def _run_half(bundle, state, log_path, images_dir, first_seq: int, last_seq: int):
    """One `run` process fed the images of images_dir, stopped by SIGTERM; (its results, stderr)."""
    node = run_node_process(["--model", str(bundle), "--mcap", str(log_path), "--queue", "256", "--state", str(state),
                             "--snapshot-every", "20p"], images_dir, last_seq)
    assert node.returncode == 0, node.stderr
    assert [d["sequence"] for d in node.results] == list(range(first_seq, last_seq + 1))
    return node.results, node.stderr


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_run_restarted_with_its_state_detects_revisits_of_frames_stored_before(tmp_path):
    bundle = make_synthetic_bundle(tmp_path / "bundle")
    images, _gt = generate_loop_sequence(N, seed=2, size=(160, 120))
    first = write_sequence(tmp_path / "first", images[:HALF], np.zeros((HALF, HALF), bool))
    second = write_sequence(tmp_path / "second", images[HALF:], np.zeros((N - HALF, N - HALF), bool))

    # The uninterrupted run, in process, over the same image files.
    loop = FrameLoop(load_detector(bundle, DetectorConfig()))
    expected = [_deterministic(loop.step_file(p, i).result.to_dict()) for i, p in enumerate(first + second)]
    loops_after = [(r["sequence"], r["verified_frame"]) for r in expected[HALF:] if r["loop"]]
    assert loops_after and all(f < HALF for _, f in loops_after)

    state = tmp_path / "state"
    docs1, _ = _run_half(bundle, state, tmp_path / "a.mcap", tmp_path / "first", 0, HALF - 1)
    assert (state / "CURRENT").is_file()
    docs2, err2 = _run_half(bundle, state, tmp_path / "b.mcap", tmp_path / "second", HALF, N - 1)
    assert "map state" in err2 and "loaded" in err2
    got = [_deterministic(d) for d in docs1 + docs2]
    assert [(r["sequence"], r["verified_frame"]) for r in got[HALF:] if r["loop"]] == loops_after
    assert got == expected


@pytest.mark.slow
@pytest.mark.timeout(120)
def test_run_refuses_a_state_of_another_bundle_in_one_line(tmp_path):
    from aefabmap_runtime.adapters.state_dir import MapStateDir, bundle_id

    bundle = make_synthetic_bundle(tmp_path / "bundle")
    other = make_synthetic_bundle(tmp_path / "other", seed=1)
    det = load_detector(other, DetectorConfig())
    with MapStateDir(tmp_path / "state", bundle_id(det.manifest)) as d:
        d.save(det.state())
    listen, _ = session_pair()
    proc = subprocess.run(CLI + ["run", "--model", str(bundle), "--key", KEY, "--listen", listen.listen[0],
                                 "--mcap", str(tmp_path / "x.mcap"), "--state", str(tmp_path / "state")],
                          capture_output=True, text=True, timeout=60, check=False)
    assert proc.returncode == 3
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "another model bundle" in lines[0]
