"""replay --check over a log set whose runs restarted from a saved map (`run --state`): each run is
replayed from the map it started with, or the check says which runs it cannot rebuild."""

from __future__ import annotations

import pytest

from aefabmap_runtime.adapters.bundle_reader import load_detector
from aefabmap_runtime.adapters.frames import encode_frame
from aefabmap_runtime.adapters.log_set import LOG_FILE_METADATA
from aefabmap_runtime.adapters.mcap_log import McapLogWriter
from aefabmap_runtime.adapters.replay import replay
from aefabmap_runtime.core.detector import DetectorConfig
from aefabmap_runtime.core.records.map_state import MapState

CONFIG = DetectorConfig(exclude=1)


@pytest.fixture(scope="module")
def frames():
    from aefabmap_runtime.tools.synthetic_route import generate_loop_sequence

    images, _ = generate_loop_sequence(14, seed=0, size=(320, 240))
    return [encode_frame(img, "png") for img in images]


def _detector():
    from aefabmap.cli.demo import default_bundle

    return load_detector(default_bundle(), CONFIG)


def _write_run(path, det, frames, seqs, run_ns, map_start):
    """One run's log file: frames[seqs] through det, with the run metadata `run` writes."""
    meta = {LOG_FILE_METADATA: {"run_started_ns": run_ns, "index": 1, "opened_ns": run_ns, "previous": None}}
    run_config = {"model": "demo"} if map_start is None else {"model": "demo", "map_start": {"frame": map_start}}
    with McapLogWriter(path, manifest=det.manifest, run_config=run_config, extra_metadata=meta) as w:
        for s in seqs:
            payload, enc = frames[s]
            from aefabmap_runtime.adapters.frames import decode_frame

            result = det.process(decode_frame(payload, enc), stamp_ns=1000 + s)
            w.write_image(payload, enc, 1000 + s, sequence=result.sequence)
            w.write_result(result)


def _state(det) -> MapState:
    st = det.state().resolve()
    return MapState(dict(st.arrays), dict(st.scalars))


def test_a_run_resumed_from_an_older_map_is_replayed_from_that_map(tmp_path, frames):
    """Run 1 processed frames 0-9 but its saved map stopped at frame 6 (kill -9 without the journal);
    run 2 resumed from it at frame 6: frames 6-9 were processed twice, from two maps."""
    first = _detector()
    saved = None
    log_dir = tmp_path / "logs"
    log_dir.mkdir()
    meta = {LOG_FILE_METADATA: {"run_started_ns": 1, "index": 1, "opened_ns": 1, "previous": None}}
    from aefabmap_runtime.adapters.frames import decode_frame

    with McapLogWriter(log_dir / "a.mcap", manifest=first.manifest, run_config={"map_start": {"frame": 0}},
                       extra_metadata=meta) as w:
        for s in range(10):
            if s == 6:
                saved = _state(first)
            result = first.process(decode_frame(*frames[s]), stamp_ns=1000 + s)
            w.write_image(*frames[s], 1000 + s, sequence=result.sequence)
            w.write_result(result)
    second = _detector()
    second.load_state(saved)
    _write_run(log_dir / "b.mcap", second, frames, range(6, 14), 2, 6)
    summary = replay(_detector(), log_dir, check=True)
    report = summary.check
    assert report.ok, report.describe()
    assert report.compared == 10 + 8 and report.matched == 18
    assert any("resumed from the map saved at frame 6" in n for n in report.notes)
    # Without the rebuild the same log set fails: the first run's map continued into the second.
    plain = _detector()
    naive = replay(plain, log_dir / "b.mcap", check=True).check
    assert not naive.ok


def test_a_run_whose_map_the_log_cannot_rebuild_is_named_and_not_compared(tmp_path, frames):
    log_dir = tmp_path / "logs"
    log_dir.mkdir()
    _write_run(log_dir / "a.mcap", _detector(), frames, range(0, 5), 1, 0)
    resumed = _detector()
    for s in range(9):  # a map at frame 9 that frames 5-8, never logged, built
        from aefabmap_runtime.adapters.frames import decode_frame

        resumed.process(decode_frame(*frames[s]), stamp_ns=1000 + s)
    _write_run(log_dir / "b.mcap", resumed, frames, range(9, 12), 2, 9)
    report = replay(_detector(), log_dir, check=True).check
    assert report.ok and report.compared == 5  # the first run only
    assert any("cannot rebuild" in n and "run 2" in n for n in report.notes)


def test_runs_without_a_recorded_map_start_are_named(tmp_path, frames):
    log_dir = tmp_path / "logs"
    log_dir.mkdir()
    _write_run(log_dir / "a.mcap", _detector(), frames, range(0, 4), 1, None)
    _write_run(log_dir / "b.mcap", _detector(), frames, range(4, 8), 2, None)
    report = replay(_detector(), log_dir, check=True).check
    assert any("does not record the map it started with" in n for n in report.notes)
    assert not report.ok  # run 2 started empty in the log, with run 1's map in the replay
