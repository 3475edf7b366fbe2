"""Chow-Liu learning benchmark on synthetic observations with realistic sparsity."""

from __future__ import annotations

import resource
import time
import tracemalloc
from dataclasses import dataclass

from aefabmap_runtime.tools.synthetic_observations import synthetic_observations
from aefabmap_trainer.chow_liu import fit_chow_liu


@dataclass
class ChowLiuBenchResult:
    images: int
    words: int
    words_per_image: int
    seconds: float
    peak_traced_mb: float
    peak_rss_mb: float


def bench_chow_liu(images: int, words: int, words_per_image: int = 300, seed: int = 0) -> ChowLiuBenchResult:
    """Time fit_chow_liu on `images` synthetic observations over `words` words.

    peak_traced_mb: peak of memory allocated during the fit (numpy/scipy buffers, tracemalloc);
    peak_rss_mb: the process's peak resident set (includes the input and the interpreter).
    """
    obs = synthetic_observations(images, words, words_per_image, seed)
    tracemalloc.start()
    t0 = time.perf_counter()
    fit_chow_liu(obs, words)
    seconds = time.perf_counter() - t0
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return ChowLiuBenchResult(images, words, words_per_image, seconds, peak / 2**20, rss)
