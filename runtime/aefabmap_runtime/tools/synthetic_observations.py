"""Synthetic observations with realistic sparsity and the FAB-MAP inference benchmark (pure)."""

from __future__ import annotations

import os
import time
from collections.abc import Iterator
from dataclasses import dataclass
from itertools import islice

import numpy as np

from aefabmap_runtime.core.kernels import compiled
from aefabmap_runtime.core.rank.fabmap import FabMap2
from aefabmap_runtime.core.rank.tree import ChowLiuTree


def observation_stream(vocabulary_size: int, words_per_obs: int = 300, seed: int = 0) -> Iterator[np.ndarray]:
    """An endless stream of observations of ~words_per_obs distinct words each (sorted int64
    arrays), drawn one at a time (constant memory however many are taken).

    Word frequencies are log-normal (sigma 0.75: the most common words are ~10x more
    frequent than the median one, as in k-means vocabularies of real images).
    """
    rng = np.random.default_rng(seed)
    weights = rng.lognormal(0.0, 0.75, vocabulary_size)
    cdf = np.cumsum(weights / weights.sum())
    k = min(words_per_obs, vocabulary_size)
    while True:
        draws = np.searchsorted(cdf, rng.random(int(k * 1.15)))
        w = np.unique(np.minimum(draws, vocabulary_size - 1))[:k]
        yield w.astype(np.int64)


def synthetic_observations(n: int, vocabulary_size: int, words_per_obs: int = 300, seed: int = 0) -> list[np.ndarray]:
    """The first n observations of :func:`observation_stream` (same arguments)."""
    return list(islice(observation_stream(vocabulary_size, words_per_obs, seed), n))


def random_tree(vocabulary_size: int, seed: int = 0) -> ChowLiuTree:
    """A random Chow-Liu tree with plausible probabilities (for benchmarks and tests)."""
    rng = np.random.default_rng(seed)
    v = vocabulary_size
    parent = np.zeros(v, np.int64)
    perm = rng.permutation(v)
    # Each word's parent is an earlier word in a random order: a random recursive tree.
    for idx in range(1, v):
        parent[perm[idx]] = perm[rng.integers(0, idx)]
    parent[perm[0]] = perm[0]
    p = rng.uniform(0.01, 0.2, v)
    a = rng.uniform(0.05, 0.9, v)
    b = rng.uniform(0.01, 0.3, v)
    a[perm[0]] = b[perm[0]] = p[perm[0]]
    return ChowLiuTree(parent, p, a, b)


@dataclass
class InferenceBenchResult:
    places: int
    words: int
    words_per_place: float
    training_observations: int
    queries: int
    median_ms: float
    p95_ms: float
    mean_ms: float
    cpu_median_ms: float  # thread CPU time per query: less sensitive to other jobs than wall time
    cpu_p95_ms: float
    load_average: float  # 1-minute load average when the queries started
    add_ms_median: float
    remove_ms_median: float  # evicting one place (CPU), what a capped map pays per frame once full
    bytes_per_place: float
    index_bytes: int
    scatter: str  # "compiled" (numba kernel) or "numpy"


def bench_inference(places: int, words: int, *, queries: int = 200, training: int = 1000, words_per_place: int = 300, seed: int = 0) -> InferenceBenchResult:
    """Time FabMap2.localize (no add) on a map of `places` synthetic places over `words` words."""
    tree = random_tree(words, seed)
    engine = FabMap2(tree, synthetic_observations(training, words, words_per_place, seed + 1))
    obs = synthetic_observations(places, words, words_per_place, seed + 2)
    add_times = []
    for i, o in enumerate(obs):
        t0 = time.perf_counter()
        engine.add(o)
        if i % max(1, places // 200) == 0:
            add_times.append(time.perf_counter() - t0)
    del obs
    qs = synthetic_observations(queries, words, words_per_place, seed + 3)
    engine.localize(qs[0], add=False)  # untimed: first-call costs (allocations, a lazy compile)
    load = os.getloadavg()[0]
    times, cpu_times = [], []
    for q in qs:
        t0, c0 = time.perf_counter(), time.thread_time()
        engine.localize(q, add=False)
        times.append(time.perf_counter() - t0)
        cpu_times.append(time.thread_time() - c0)
    t = np.array(times) * 1e3
    c = np.array(cpu_times) * 1e3
    nbytes = engine.nbytes()
    remove_times = []
    for pid in range(0, places, max(1, places // 200)):  # after the queries: they saw the full map
        c0 = time.thread_time()
        engine.remove(pid)
        remove_times.append(time.thread_time() - c0)
    return InferenceBenchResult(
        places=places,
        words=words,
        words_per_place=float(np.mean([len(q) for q in qs])),
        training_observations=training,
        queries=queries,
        median_ms=float(np.median(t)),
        p95_ms=float(np.percentile(t, 95)),
        mean_ms=float(t.mean()),
        cpu_median_ms=float(np.median(c)),
        cpu_p95_ms=float(np.percentile(c, 95)),
        load_average=round(load, 2),
        add_ms_median=float(np.median(add_times) * 1e3),
        remove_ms_median=float(np.median(remove_times) * 1e3) if remove_times else 0.0,
        bytes_per_place=nbytes / max(1, places),
        index_bytes=nbytes,
        scatter=compiled.backend(),
    )
