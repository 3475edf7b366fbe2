"""Scorer interface: FAB-MAP and BoW behind one protocol, BoW removal, caps with either scorer."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from aefabmap import InputError
from aefabmap_runtime.adapters.bundle_reader import load_bundle, load_detector
from aefabmap_runtime.core.rank.bow import BowIndex
from aefabmap_runtime.core.detector import DetectorConfig
from aefabmap_runtime.core.rank.fabmap import FabMap2
from aefabmap_runtime.core.rank.scorer import BowScorer, FabMapScorer
from tests.conftest import make_synthetic_bundle

FIXTURE = Path(__file__).parents[1] / "data" / "fabmap_stream_b5eb575.json"


def fabmap_stream() -> tuple[dict, list]:
    """The stream the fixture was recorded from: 12 places (30 words each) visited twice, the
    second lap with 6 of 30 words replaced; (config name -> DetectorConfig, name -> stream)."""
    rng = np.random.default_rng(7)
    base = [rng.integers(0, 64, 30) for _ in range(12)]
    stream = base + [np.concatenate([w[:24], rng.integers(0, 64, 6)]) for w in base]
    configs = {
        "plain": DetectorConfig(exclude=3),
        "llr_motion_cap": DetectorConfig(exclude=2, fabmap_score="llr", motion_model=True, max_places=6),
    }
    return configs, stream


def test_fabmap_results_are_those_of_the_code_before_the_interface(tmp_path):
    bundle = make_synthetic_bundle(tmp_path / "b", vocabulary_size=64, seed=4)
    recorded = json.loads(FIXTURE.read_text())
    fields = recorded["fields"]
    configs, stream = fabmap_stream()
    for name, cfg in configs.items():
        det = load_detector(bundle, cfg)
        got = [[getattr(r, f) for f in fields] for r in (det.process_words(w) for w in stream)]
        want = recorded["streams"][name]
        assert len(got) == len(want)
        for i, (g, w) in enumerate(zip(got, want)):
            for f, a, b in zip(fields, g, w):
                if isinstance(b, float):
                    assert a == pytest.approx(b, rel=1e-12, abs=1e-15), (name, i, f)
                else:
                    assert a == b, (name, i, f)


def _scorers(bundle_path: Path):
    b = load_bundle(bundle_path)
    return {
        "fabmap": FabMapScorer(FabMap2(b.tree, b.training_observations)),
        "bow": BowScorer(BowIndex(b.vocabulary_size, b.training_observations)),
    }


@pytest.mark.parametrize("name", ["fabmap", "bow"])
def test_both_scorers_add_remove_rank_and_reuse_ids(synthetic_bundle, name):
    scorer = _scorers(synthetic_bundle)[name]
    rng = np.random.default_rng(1)
    places = [rng.integers(0, 64, 25) for _ in range(4)]
    assert scorer.rank(places[0]).best is None and scorer.rank(places[0]).score == 0.0
    ids = [scorer.add(w) for w in places]
    assert ids == [0, 1, 2, 3] and scorer.n_alive == 4
    r = scorer.rank(places[2])
    assert r.best == 2 and r.order.shape == r.scores.shape == (4,)
    before = scorer.nbytes()
    scorer.remove(2)
    r = scorer.rank(places[2])
    assert r.best != 2 and r.order[2] == -np.inf and r.scores[2] == 0.0
    assert scorer.n_alive == 3 and list(scorer.alive) == [True, True, False, True]
    assert scorer.nbytes() < before
    assert scorer.add(places[2]) == 2 and scorer.n_places == 4  # the freed id is reused
    assert scorer.rank(places[2]).best == 2
    with pytest.raises(InputError):
        scorer.remove(7)
    if name == "fabmap":
        assert r.probability is not None and r.llr is not None and r.p_new is not None
    else:
        assert r.probability is r.llr is r.p_new is None and r.score == pytest.approx(r.scores[r.best])


def test_bow_removal_leaves_the_other_places_scores_unchanged(synthetic_bundle):
    b = load_bundle(synthetic_bundle)
    rng = np.random.default_rng(3)
    places = [rng.integers(0, 64, 30) for _ in range(6)]
    query = rng.integers(0, 64, 30)
    full, kept = BowIndex(64, b.training_observations), BowIndex(64, b.training_observations)
    for w in places:
        full.add(w)
    for w in places[::2]:
        kept.add(w)
    for pid in (1, 3, 5):
        full.remove(pid)
    assert np.allclose(full.similarity(query)[::2], kept.similarity(query), rtol=0, atol=1e-15)
    assert np.all(full.similarity(query)[1::2] == 0.0)
    # Removing everything and adding the same places again gives the same memory.
    full2 = BowIndex(64, b.training_observations)
    for w in places:
        full2.add(w)
    size = full2.nbytes()
    for pid in range(6):
        full2.remove(pid)
    for w in places:
        full2.add(w)
    assert full2.nbytes() == size


def test_bow_honours_max_places(synthetic_bundle):
    det = load_detector(synthetic_bundle, DetectorConfig(scorer="bow", exclude=0, max_places=5))
    rng = np.random.default_rng(2)
    evicted = []
    for _ in range(30):
        r = det.process_words(rng.integers(0, 64, 40))
        evicted.append(r.evicted_place)
        assert det.n_places <= 5 and (r.best_place is None or r.best_place < 5)
    assert any(e is not None for e in evicted) and det.scorer.n_places == 5


def test_bow_memory_cap_holds_over_a_long_run(tmp_path):
    bundle = make_synthetic_bundle(tmp_path / "b", vocabulary_size=500)
    cap_mb = 0.05
    det = load_detector(bundle, DetectorConfig(scorer="bow", exclude=3, memory_mb=cap_mb))
    rng = np.random.default_rng(3)
    sizes = []
    for _ in range(1200):
        before = det.n_places
        r = det.process_words(rng.integers(0, 500, 40))
        sizes.append(det.map_bytes())
        if r.inserted_place is not None and det.n_places <= before:
            assert r.evicted_place is not None  # every eviction is reported, place 0 included
    assert max(sizes) <= cap_mb * 2**20
    assert det.n_places < 1200 - 3  # places were evicted
    # Flat once at the cap: the last 400 frames do not grow the map.
    assert max(sizes[-400:]) <= max(sizes[400:800]) * 1.05
