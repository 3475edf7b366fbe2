"""Localization against a map built once (--localize with --state DIR), as processes: the map is
loaded read-only, later frames verify against its places, none of them is inserted, and the state
directory is byte for byte what it was, after a clean stop, a kill -9 and a replay."""

from __future__ import annotations

import signal
import subprocess

import numpy as np
import pytest

from aefabmap_runtime.tools.localize_eval import state_digest
from aefabmap_runtime.tools.synthetic_route import generate_loop_sequence, write_sequence
from tests.conftest import make_synthetic_bundle

from .stream_fakes import CLI, KEY, run_node_process, session_pair

N, HALF = 120, 60  # two laps: frames 60.. revisit frames 0..59


@pytest.fixture(scope="module")
def mapped(tmp_path_factory):
    """A bundle, the second lap's images, and a state directory holding the map of the first lap."""
    tmp = tmp_path_factory.mktemp("localize")
    bundle = make_synthetic_bundle(tmp / "bundle")
    images, _ = generate_loop_sequence(N, seed=2, size=(160, 120))
    write_sequence(tmp / "first", images[:HALF], np.zeros((HALF, HALF), bool))
    write_sequence(tmp / "second", images[HALF:], np.zeros((N - HALF, N - HALF), bool))
    state = tmp / "state"
    node = run_node_process(["--model", str(bundle), "--mcap", str(tmp / "map.mcap"), "--queue", "256",
                             "--state", str(state)], tmp / "first", HALF - 1)
    assert node.returncode == 0, node.stderr
    return bundle, tmp, state


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_run_localize_verifies_against_the_map_and_never_writes_it(mapped, tmp_path):
    bundle, tmp, state = mapped
    before = state_digest(state)
    node = run_node_process(["--model", str(bundle), "--mcap", str(tmp_path / "loc.mcap"), "--queue", "256",
                             "--state", str(state), "--localize"], tmp / "second", N - 1)
    assert node.returncode == 0, node.stderr
    assert "localizing against the map" in node.stderr
    assert [d["sequence"] for d in node.results] == list(range(HALF, N))  # numbered on from the map's frames
    loops = [(d["sequence"], d["verified_frame"]) for d in node.results if d["verified"]]
    assert loops and all(f < HALF for _, f in loops)  # every match is a place of the map
    # The frames the mapping run still held back (the default insertion delay, 50) enter on their
    # schedule, each 50 frames after its own, evicting nothing; then the map stays as it is.
    entered = [(d["sequence"], d["inserted_frame"]) for d in node.results if d["inserted_frame"] is not None]
    assert entered == [(f + 50, f) for f in range(HALF - 50, HALF)]
    assert all(d["evicted_place"] is None for d in node.results)
    places = [d["n_places"] for d in node.results]
    assert places[0] > 0 and places[-1] == places[0] + len(entered) - 1 and places == sorted(places)
    assert state_digest(state) == before

    # The same frames replayed from the localize run's log, against the same map: same matches, DIR unchanged.
    out = subprocess.run(CLI + ["replay", str(tmp_path / "loc.mcap"), "--model", str(bundle), "--state", str(state),
                                "--localize"], capture_output=True, text=True, timeout=240, check=False)
    assert out.returncode == 0, out.stderr
    assert state_digest(state) == before


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_a_localize_node_killed_mid_run_leaves_the_state_unchanged(mapped, tmp_path):
    bundle, tmp, state = mapped
    before = state_digest(state)
    node = run_node_process(["--model", str(bundle), "--mcap", str(tmp_path / "k.mcap"), "--queue", "256",
                             "--state", str(state), "--localize"], tmp / "second", HALF + 30,
                            stop_signal=signal.SIGKILL)
    assert node.returncode == -signal.SIGKILL
    assert state_digest(state) == before


@pytest.mark.timeout(120)
def test_localize_without_a_map_is_one_line(tmp_path):
    bundle = make_synthetic_bundle(tmp_path / "bundle")
    listen, _ = session_pair()
    base = CLI + ["run", "--model", str(bundle), "--key", KEY, "--listen", listen.listen[0],
                  "--mcap", str(tmp_path / "x.mcap"), "--localize"]
    no_state = subprocess.run(base, capture_output=True, text=True, timeout=60, check=False)
    assert no_state.returncode == 2 and len(no_state.stderr.strip().splitlines()) == 1
    assert "--localize needs --state" in no_state.stderr
    (tmp_path / "empty").mkdir()
    empty = subprocess.run(base + ["--state", str(tmp_path / "empty")], capture_output=True, text=True, timeout=60,
                           check=False)
    assert empty.returncode == 3 and len(empty.stderr.strip().splitlines()) == 1
    assert "holds no places" in empty.stderr
    assert list((tmp_path / "empty").iterdir()) == []  # not even a lock file was written
    missing = subprocess.run(base + ["--state", str(tmp_path / "missing")], capture_output=True, text=True,
                             timeout=60, check=False)
    assert missing.returncode == 3 and not (tmp_path / "missing").exists()
