"""FAB-MAP 2.0 engine: the reference vector of docs/fabmap2.md and agreement with a dense brute force."""

from __future__ import annotations

import math

import numpy as np
import pytest

from aefabmap import ChowLiuTree, FabMap2, InputError
from aefabmap_runtime.tools.synthetic_observations import random_tree


def reference_tree() -> ChowLiuTree:
    return ChowLiuTree(parent=[0, 0], p=[0.2, 0.1], p_given_parent=[0.2, 0.6], p_given_not_parent=[0.2, 0.05])


def test_reference_tables():
    t = FabMap2(reference_tree(), [[0], [1]]).tables
    np.testing.assert_allclose(t.d1, [-0.4413119077, -0.2496872383], atol=1e-9)
    np.testing.assert_allclose(t.d2, [0.0, -1.9567482036], atol=1e-9)
    np.testing.assert_allclose(t.d3, [2.4638360865, 3.0067877831], atol=1e-9)
    np.testing.assert_allclose(t.d4, t.d3, atol=1e-12)


def test_reference_loglik_and_posterior():
    fm = FabMap2(reference_tree(), [[0], [1]])
    for obs in ([0, 1], [1], [0]):
        fm.add(obs)
    np.testing.assert_allclose(fm.loglik([0]), [-0.183911263, -2.206435442, 2.022524179], atol=1e-9)
    assert fm.loglik_new([0]) == pytest.approx(1.343839449, abs=1e-9)
    loc = fm.localize([0], add=False)
    np.testing.assert_allclose([loc.p_new, *loc.p_places], [0.3102379, 0.0692863, 0.0113372, 0.6091386], atol=1e-7)
    assert loc.best_place == 2 and loc.best_probability == pytest.approx(0.6091386, abs=1e-7)
    assert math.isclose(loc.p_new + loc.p_places.sum(), 1.0)


# --- an independent, dense, scalar implementation of the formulas (openFABMAP's PzqGL form) ---
def _g(p, a, b, z, zp, l, pzge, pzgne):
    cond = a if zp else b

    def pz_e(zz, e):
        pr = pzge if e else pzgne
        return pr if zz else 1 - pr

    def marg(zz):
        return p if zz else 1 - p

    def c(zz):
        return cond if zz else 1 - cond

    num1, num0 = pz_e(l, 1) * p, pz_e(l, 0) * (1 - p)
    total = 0.0
    for e, pe in ((1, num1 / (num1 + num0)), (0, num0 / (num1 + num0))):
        alpha = marg(z) * pz_e(1 - z, e) * c(1 - z)
        beta = marg(1 - z) * pz_e(z, e) * c(z)
        total += pe * beta / (alpha + beta)
    return total


def brute_loglik(tree: ChowLiuTree, z: np.ndarray, l: np.ndarray, pzge=0.39, pzgne=0.0) -> float:
    """sum_q log G(z_q, z_pq, l_q) - sum_q log G(z_q, z_pq, 0): the index's per-query offset removed."""
    s = 0.0
    for q in range(tree.size):
        zp = int(z[tree.parent[q]])
        args = (tree.p[q], tree.p_given_parent[q], tree.p_given_not_parent[q], int(z[q]), zp)
        s += math.log(_g(*args, int(l[q]), pzge, pzgne)) - math.log(_g(*args, 0, pzge, pzgne))
    return s


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("pzgne", [0.0, 0.05])
def test_agrees_with_dense_brute_force(seed, pzgne, kernels):
    rng = np.random.default_rng(seed)
    v = 40
    tree = random_tree(v, seed)
    places = (rng.random((12, v)) < 0.25).astype(int)
    training = (rng.random((7, v)) < 0.25).astype(int)
    fm = FabMap2(tree, [np.flatnonzero(t) for t in training], pzgne=pzgne)
    for pl in places:
        fm.add(np.flatnonzero(pl))
    for _ in range(5):
        z = (rng.random(v) < 0.3).astype(int)
        expected = np.array([brute_loglik(tree, z, pl, pzgne=pzgne) for pl in places])
        np.testing.assert_allclose(fm.loglik(np.flatnonzero(z)), expected, atol=1e-9)
        t_ll = np.array([brute_loglik(tree, z, t, pzgne=pzgne) for t in training])
        new = np.logaddexp.reduce(t_ll) - np.log(len(training))
        assert fm.loglik_new(np.flatnonzero(z)) == pytest.approx(new, abs=1e-9)
        loc = fm.localize(np.flatnonzero(z), add=False)
        logs = np.r_[new, expected]
        probs = 0.99 * np.exp(logs - np.logaddexp.reduce(logs)) + 0.01 / logs.size
        np.testing.assert_allclose(np.r_[loc.p_new, loc.p_places], probs, atol=1e-12)


def test_naive_bayes_ignores_the_tree():
    rng = np.random.default_rng(5)
    v = 30
    t1, t2 = random_tree(v, 1), random_tree(v, 2)
    # Same marginals, different structure: naive Bayes must not see the difference.
    t2 = ChowLiuTree(t2.parent, t1.p, t2.p_given_parent, t2.p_given_not_parent)
    train = [np.flatnonzero(rng.random(v) < 0.3) for _ in range(5)]
    a, b = FabMap2(t1, train, naive_bayes=True), FabMap2(t2, train, naive_bayes=True)
    for _ in range(4):
        o = np.flatnonzero(rng.random(v) < 0.3)
        a.add(o)
        b.add(o)
    q = np.flatnonzero(rng.random(v) < 0.3)
    np.testing.assert_allclose(a.loglik(q), b.loglik(q), atol=1e-12)


def test_localize_adds_and_ids_are_sequential():
    fm = FabMap2(reference_tree(), [[0], [1]])
    r0 = fm.localize([0])
    assert r0.place_id == 0 and r0.best_place is None and r0.p_places.size == 0
    assert r0.p_new == pytest.approx(1.0)
    r1 = fm.localize([1])
    assert r1.place_id == 1 and r1.p_places.size == 1


def test_remove_masks_place_and_keeps_ids():
    rng = np.random.default_rng(3)
    v = 50
    fm = FabMap2(random_tree(v, 3), [np.flatnonzero(rng.random(v) < 0.2) for _ in range(4)])
    obs = [np.flatnonzero(rng.random(v) < 0.2) for _ in range(6)]
    for o in obs:
        fm.add(o)
    q = obs[2]
    before = fm.loglik(q)
    fm.remove(2)
    after = fm.loglik(q)
    assert np.isneginf(after[2])
    np.testing.assert_allclose(np.delete(after, 2), np.delete(before, 2), atol=1e-12)
    assert fm.localize(q, add=False).p_places[2] == 0.0
    with pytest.raises(InputError):
        fm.remove(2)
    assert fm.add(obs[0]) == 2  # the freed id is reused: memory stays bounded
    assert fm.add(obs[1]) == 6
    np.testing.assert_allclose(fm.loglik(q)[:2], before[:2], atol=1e-12)


def test_motion_model_matches_formula():
    rng = np.random.default_rng(0)
    v = 60
    tree = random_tree(v, 0)
    train = [np.flatnonzero(rng.random(v) < 0.2) for _ in range(5)]
    fm = FabMap2(tree, train, motion_model=True)
    for _ in range(5):
        fm.add(np.flatnonzero(rng.random(v) < 0.2))
    first = fm.localize(np.flatnonzero(rng.random(v) < 0.2), add=False)
    prior = first.p_places
    q = np.flatnonzero(rng.random(v) < 0.2)
    loc = fm.localize(q, add=False)
    # docs/fabmap2.md: m_0 = l_0 + log Pnew; m_i = l_i + log((2(1-mB) pi_{i-1} + pi_i + 2 mB pi_{i+1}) / 3).
    padded = np.r_[prior[0], prior, prior[-1]]
    mix = (2 * 0.5 * padded[:-2] + prior + 2 * 0.5 * padded[2:]) / 3
    logs = np.r_[loc.loglik_new + np.log(0.9), loc.loglik + np.log(mix)]
    expected = 0.99 * np.exp(logs - np.logaddexp.reduce(logs)) + 0.01 / logs.size
    np.testing.assert_allclose(np.r_[loc.p_new, loc.p_places], expected, atol=1e-12)


def test_bad_observations_raise():
    fm = FabMap2(reference_tree(), [[0], [1]])
    with pytest.raises(InputError, match="word ids"):
        fm.add([5])
    with pytest.raises(InputError):
        fm.add([[0, 1]])
    with pytest.raises(InputError, match="training observation"):
        FabMap2(reference_tree(), [])


def test_tree_validation():
    with pytest.raises(InputError, match="root"):
        ChowLiuTree([1, 0], [0.2, 0.1], [0.2, 0.6], [0.2, 0.05])
    with pytest.raises(InputError, match="inside"):
        ChowLiuTree([0, 0], [0.2, 1.0], [0.2, 0.6], [0.2, 0.05])
    with pytest.raises(InputError, match="shape"):
        ChowLiuTree([0, 0], [0.2], [0.2, 0.6], [0.2, 0.05])


def test_places_cost_at_most_2kb_at_300_words():
    """int32 postings grown by a quarter plus uint16 word lists: <= 2 KB per 300-word place."""
    from aefabmap_runtime.tools.synthetic_observations import synthetic_observations

    words = 2000
    engine = FabMap2(random_tree(words, 3), synthetic_observations(20, words, 300, 4))
    places = synthetic_observations(3000, words, 300, 5)
    for obs in places:
        engine.add(obs)
    assert engine.places.place_words(0).dtype == np.uint16
    assert all(engine.places.postings.ids(q).dtype == np.int32 for q in range(words))
    assert engine.nbytes() / len(places) <= 2048


def test_removal_then_reuse_scores_like_a_fresh_map():
    """Postings compacted on removal: a reused id scores only its new words."""
    words = 300
    tree = random_tree(words, 7)
    rng = np.random.default_rng(7)
    obs = [rng.choice(words, 40, replace=False) for _ in range(30)]
    training = [rng.choice(words, 40, replace=False) for _ in range(10)]
    a = FabMap2(tree, training)
    for o in obs[:20]:
        a.add(o)
    for pid in (3, 11, 0):
        a.remove(pid)
    for o in obs[20:23]:
        a.add(o)  # free ids are reused last-removed first: 0, 11, 3
    b = FabMap2(tree, training)
    kept = [o for i, o in enumerate(obs[:20]) if i not in (3, 11, 0)]
    for o in kept:
        b.add(o)
    q = obs[25]
    la, lb = a.loglik(q), b.loglik(q)
    assert la.size == 20 and lb.size == 17
    expected = {0: obs[20], 11: obs[21], 3: obs[22]}
    for pid, o in expected.items():
        c = FabMap2(tree, training)
        c.add(o)
        assert la[pid] == pytest.approx(c.loglik(q)[0], rel=1e-12, abs=1e-9)
    assert np.allclose(np.delete(la, [0, 3, 11]), lb, rtol=1e-12)
    assert a.loglik_new(q) == b.loglik_new(q)


def test_an_empty_copy_shares_the_model_and_scores_as_a_fresh_one():
    words = 300
    tree = random_tree(words, 5)
    rng = np.random.default_rng(5)
    obs = [rng.choice(words, 40, replace=False) for _ in range(12)]
    training = [rng.choice(words, 40, replace=False) for _ in range(10)]
    own = FabMap2(tree, training, motion_model=True)
    for o in obs[:6]:
        own.localize(o)
    copy, fresh = own.empty_like(), FabMap2(tree, training, motion_model=True)
    assert copy.n_places == 0 and copy._prior is None
    assert copy.tables is own.tables and copy._training is own._training  # shared, not rebuilt
    for o in obs[6:]:
        a, b = copy.localize(o), fresh.localize(o)
        assert np.array_equal(a.loglik, b.loglik) and a.loglik_new == b.loglik_new and a.p_new == b.p_new
    assert own.n_places == 6  # the original's places are its own


def test_training_observations_are_made_word_sets_as_one_at_a_time():
    from aefabmap_runtime.core.rank.fabmap import as_word_set, as_word_sets

    rng = np.random.default_rng(3)
    observations = [rng.integers(0, 50, rng.integers(0, 30)) for _ in range(40)]
    observations += [[], [7, 7, 1], np.array([49], np.uint16), (0,)]
    sets = as_word_sets(observations, 50)
    assert len(sets) == len(observations)
    for got, obs in zip(sets, observations):
        want = as_word_set(obs, 50)
        assert got.dtype == want.dtype and np.array_equal(got, want)
    assert as_word_sets([], 50) == [] and [s.size for s in as_word_sets([[], []], 50)] == [0, 0]


@pytest.mark.parametrize("bad", [[[1, 2], [50]], [[0], [-1]], [[[1, 2]]], [[0.5]]])
def test_a_training_observation_outside_the_vocabulary_is_an_input_error(bad):
    from aefabmap_runtime.core.rank.fabmap import as_word_sets

    with pytest.raises(InputError):
        as_word_sets(bad, 50)


def test_distinct_sorted_is_numpys_unique():
    from aefabmap_runtime.core.rank.fabmap import distinct_sorted

    rng = np.random.default_rng(4)
    for values in (np.zeros(0, np.int64), np.array([3]), np.array([2, 2]), rng.integers(0, 40, 300),
                   rng.integers(-5, 5, 17).astype(np.int32)):
        got, want = distinct_sorted(values), np.unique(values)
        assert got.dtype == want.dtype and np.array_equal(got, want)
