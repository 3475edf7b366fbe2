"""The map a run keeps on disk (runtime/aefabmap_runtime/adapters/node_state.py): a state built with
other settings loads with one warning naming them; the live node's directory, journal and
snapshotter keep every frame and are closed in order."""

from __future__ import annotations

import logging

import pytest

from aefabmap.cli.options import default_bundle
from aefabmap_runtime.adapters.bundle_reader import load_detector
from aefabmap_runtime.adapters.node_state import NodeState, open_state
from aefabmap_runtime.adapters.state_dir import MapStateDir, SnapshotPolicy, bundle_id
from aefabmap_runtime.core.decide.candidates import CandidateConfig
from aefabmap_runtime.core.detector import DetectorConfig
from aefabmap_runtime.errors import StateError
from aefabmap_runtime.tools.synthetic_route import generate_loop_sequence
from tests.conftest import make_synthetic_bundle

LOG = logging.getLogger("test.state")


def test_a_state_built_with_other_settings_loads_with_a_warning_naming_them(tmp_path, caplog):
    bundle = make_synthetic_bundle(tmp_path / "bundle", vocabulary_size=64)
    built = load_detector(bundle, DetectorConfig(exclude=2))
    images, _ = generate_loop_sequence(8, seed=1, size=(160, 120))
    for i, img in enumerate(images):
        built.process(img, i)
    with MapStateDir(tmp_path / "state", bundle_id(built.manifest)) as d:
        d.save(built.state())

    same = load_detector(bundle, DetectorConfig(exclude=2))
    with caplog.at_level(logging.INFO, logger="test.state"):
        open_state(tmp_path / "state", same, LOG).close()
    assert same.n_places == built.n_places and "other detector settings" not in caplog.text

    caplog.clear()
    other = load_detector(bundle, DetectorConfig(exclude=3, candidates=CandidateConfig(top_k=2)))
    with caplog.at_level(logging.INFO, logger="test.state"):
        open_state(tmp_path / "state", other, LOG).close()
    assert other.n_places == built.n_places
    warning = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warning) == 1 and "candidates.top_k" in warning[0] and "exclude" in warning[0]


def _run_frames(state: NodeState, detector, images, first: int) -> None:
    """What the node does per frame: process it, then let the snapshotter (and journal) see it."""
    for i, img in enumerate(images):
        detector.process(img, first + i)
        state.snapshotter.after_frame()


def test_a_node_state_keeps_every_frame_and_the_next_run_continues_it(tmp_path, caplog):
    images, _ = generate_loop_sequence(24, seed=3, size=(160, 120))
    path = tmp_path / "state"
    first = load_detector(default_bundle(), DetectorConfig(exclude=2))
    state = NodeState(path, first, SnapshotPolicy(seconds=None, places=5), LOG)
    try:
        _run_frames(state, first, images[:12], 0)
        state.snapshotter.final()
        with caplog.at_level(logging.INFO, logger="test.state"):
            report = state.finish()
    finally:
        state.close()
    assert (report.frames_processed, report.frames_kept, report.frames_not_written) == (12, 12, 0)
    assert report.places_kept == first.n_places
    assert any(m.startswith("map state saved to") for m in caplog.messages)
    assert any(m.startswith("state: ") for m in caplog.messages)

    second = load_detector(default_bundle(), DetectorConfig(exclude=2))
    state = NodeState(path, second, SnapshotPolicy(), LOG)  # the lock was released: it opens again
    try:
        assert (second.next_sequence, second.n_places) == (12, first.n_places)
        _run_frames(state, second, images[12:], 12)  # no snapshot due: the journal keeps them
        report = state.finish()
    finally:
        state.close()
    assert (report.frames_processed, report.frames_kept) == (24, 24)

    third = load_detector(default_bundle(), DetectorConfig(exclude=2))
    open_state(path, third, LOG).close()  # snapshot, then the journal's frames
    assert third.next_sequence == 24 and third.n_places == second.n_places


def test_a_state_directory_in_use_is_a_state_error_and_nothing_stays_open(tmp_path):
    detector = load_detector(default_bundle(), DetectorConfig(exclude=2))
    with MapStateDir(tmp_path / "state", bundle_id(detector.manifest)):
        with pytest.raises(StateError, match="in use by another process"):
            NodeState(tmp_path / "state", detector, SnapshotPolicy(), LOG)
    NodeState(tmp_path / "state", detector, SnapshotPolicy(), LOG).close()
