"""Soak benchmark (runtime/aefabmap_runtime/tools/soak_bench.py): flatness verdict, log disk usage, the core phase
at tiny counts (a real detector on the shipped bundle, in a spawned process)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from aefabmap.cli.demo import default_bundle
from aefabmap_runtime.errors import BundleError, ConfigError
from aefabmap_runtime.tools.soak_bench import (
    SoakConfig,
    bench_soak,
    flatness,
    flatness_at_cap,
    log_disk_usage,
)
from aefabmap_runtime.tools.synthetic_observations import (
    observation_stream,
    synthetic_observations,
)
from aefabmap_runtime.tools.synthetic_route import random_views


def _samples(rss):
    return [{"frames": 1000 * (i + 1), "rss_mb": r} for i, r in enumerate(rss)]


def test_flatness_judges_only_after_warmup():
    # Growth during warm-up (100 -> 150) is ignored; 150.0..153.5 afterwards is within 5 MB.
    f = flatness(_samples([100.0, 150.0, 151.0, 153.5, 152.0]), "frames", 2000, 5.0)
    assert f["samples"] == 4 and f["first"] == 150.0 and f["last"] == 152.0
    assert f["range_mb"] == 3.5 and f["growth_mb"] == 2.0 and f["met"] is True


def test_flatness_fails_on_growth_and_cannot_judge_one_sample():
    f = flatness(_samples([100.0, 101.0, 104.0, 107.0]), "frames", 1000, 5.0)
    assert f["range_mb"] == 7.0 and f["met"] is False
    one = flatness(_samples([100.0, 101.0]), "frames", 2000, 5.0)
    assert one["samples"] == 1 and one["met"] is None
    missing = flatness([{"frames": 5000, "rss_mb": None}, *_samples([1.0])], "frames", 0, 5.0)
    assert missing["samples"] == 1  # a sample without RSS is not counted


def test_log_disk_usage_counts_mcap_files_only(tmp_path):
    (tmp_path / "a-0001.mcap").write_bytes(b"x" * 100)
    (tmp_path / "a-0002.mcap").write_bytes(b"x" * 250)
    (tmp_path / "notes.txt").write_bytes(b"x" * 999)
    assert log_disk_usage(tmp_path) == {"files": 2, "bytes": 350, "largest_bytes": 250}
    assert log_disk_usage(tmp_path / "absent") == {"files": 0, "bytes": 0, "largest_bytes": 0}


def test_observation_stream_matches_the_list_and_views_do_not_repeat():
    head = list(itertools.islice(observation_stream(400, 50, seed=5), 20))
    ref = synthetic_observations(20, 400, 50, seed=5)
    assert all(np.array_equal(a, b) for a, b in zip(head, ref))
    views = list(itertools.islice(random_views(seed=1, size=(64, 48)), 6))
    assert all(v.shape == (48, 64) and v.dtype == np.uint8 for v in views)
    assert all(not np.array_equal(a, b) for a, b in itertools.combinations(views, 2))


def test_config_refuses_bad_values():
    with pytest.raises(ConfigError):
        SoakConfig(bundle="x", frames=0, observations=0)
    with pytest.raises(ConfigError):
        SoakConfig(bundle="x", rate_hz=-1)
    with pytest.raises(ConfigError):
        SoakConfig(bundle="x", frame_checkpoints=(0, 10))
    with pytest.raises(BundleError):
        bench_soak(SoakConfig(bundle="/nonexistent/bundle", frames=0, observations=10))


@pytest.mark.slow
@pytest.mark.timeout(300)
@pytest.mark.parametrize("vocabulary", [0, 2000])
def test_core_phase_samples_rss_at_the_checkpoints(vocabulary):
    n, cap = 400, 20
    doc = bench_soak(SoakConfig(
        bundle=str(default_bundle()), frames=0, observations=n, max_places=cap,
        observation_checkpoints=(100, 300, 5000), warmup_observations=100, core_vocabulary=vocabulary,
        core_words=100,
    ))
    assert doc["benchmark"] == "soak" and doc["pipeline"] is None
    core = doc["core"]
    # Checkpoints within the count, plus the count itself; 5000 is beyond it.
    assert list(core["rss_mb_at"]) == ["100", "300", "400"]
    assert all(isinstance(v, float) and v > 10 for v in core["rss_mb_at"].values())
    assert [s["observations"] for s in core["checkpoints"]] == [100, 300, 400]
    assert core["observations"] == n and core["stopped_at_max_seconds"] is False
    # The cap holds and places keep being evicted: every frame past cap + exclude (50) evicts one.
    assert core["places"]["last"] == cap and core["places"]["id_range"] <= 64
    assert core["evictions"] == n - 50 - cap
    assert core["vocabulary_size"] == (vocabulary or 500)
    f = core["rss_flat"]
    assert f["samples"] >= 3 and f["met"] in (True, False) and f["range_mb"] >= 0
    assert set(f) >= {"first", "last", "min", "max", "growth_mb", "range_mb", "met"}
    # Full after exclude (50) + cap (20) observations; samples every 2 observations.
    assert core["rss_flat_at_cap"]["cap_reached_at"] == 70


def test_flatness_at_cap_starts_where_the_map_is_full():
    samples = [{"observations": n, "rss_mb": r, "places": p}
               for n, r, p in [(10, 60.0, 5), (20, 70.0, 20), (30, 71.0, 20), (40, 71.5, 20)]]
    f = flatness_at_cap(samples, "observations", 20, 5.0)
    assert f["cap_reached_at"] == 20 and f["first"] == 70.0 and f["range_mb"] == 1.5 and f["met"] is True
    never = flatness_at_cap(samples, "observations", 50, 5.0)
    assert never["cap_reached_at"] is None and never["met"] is None
