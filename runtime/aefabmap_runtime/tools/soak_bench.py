"""Soak benchmark: resident memory over a long run with the map at its cap (`aefabmap bench soak`).

Pure of argparse; :func:`bench_soak` returns a JSON-able dict with up to two phases:

- ``pipeline``: a real ``aefabmap run`` child (``--max-places``, MCAP log into a directory with
  rotation ``--mcap-max-mb`` and ``--log-budget-mb``) fed ``frames`` synthetic frames over loopback
  Zenoh from this process. Frames are random views of the synthetic world
  (synthetic_route.random_views), rendered and JPEG-encoded one by one, so no two are alike and
  every frame becomes a place (delayed insertion) that later evicts the least recently used one.
  Paced at ``rate_hz``, or closed loop (``rate_hz`` 0: a frame is published when the result of
  the one ``window`` frames earlier came back); frames not answered are counted. The node's RSS
  (``/proc/<pid>/status`` VmRSS) and the log set on disk (files, bytes) are sampled at the frame
  counts of ``frame_checkpoints`` (frames published) and every ``sample_period_s``.
- ``core``: ``observations`` synthetic word sets (synthetic_observations.observation_stream: the
  bundle's vocabulary, its mean words per training image) through the detector core
  (``LoopClosureDetector.process_words``: FAB-MAP, delayed insertion, LRU eviction at the same
  cap), no images, in a freshly spawned single-threaded process whose own RSS is sampled at
  ``observation_checkpoints`` and every 1/200 of the run.

Flatness: RSS samples from ``warmup_*`` on (the cap is reached after max_places + exclude
frames); ``range_mb`` = max - min of them, ``met`` when range_mb <= ``flat_mb``
(``rss_flat``); ``rss_flat_at_cap``: the same from the first sample with the map full.
"""

from __future__ import annotations

import threading
import time
import uuid
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from aefabmap_runtime.errors import BundleError, ConfigError, TransportError
from aefabmap_runtime.core.records.messages import FrameResult, StatsMessage
from aefabmap_runtime.tools.node_process import (
    ResultCollector,
    bench_workdir,
    connect_when_listening,
    free_tcp_port,
    process_rss_mb,
    start_run_node,
    stop_node,
)
from aefabmap_runtime.tools.stream_bench import (
    _stats,
    load_average,
    machine_info,
    run_spawned_single_thread,
)

FRAME_CHECKPOINTS = (1_000, 10_000, 50_000, 100_000)
OBSERVATION_CHECKPOINTS = (1_000, 10_000, 100_000, 500_000, 1_000_000)


@dataclass(frozen=True)
class SoakConfig:
    """Settings of :func:`bench_soak`. Counts in frames/observations, rates in Hz, sizes in MB.

    frames / observations: length of the pipeline / core phase (0 skips it). max_places: the
    map cap of both. rate_hz: publish rate of the pipeline phase (0: closed loop with `window`
    frames in flight). size: (width, height) of the frames. mcap_max_mb / log_budget_mb /
    image_every / queue: the node's log rotation, log budget, image logging and ring size.
    *_checkpoints: counts where RSS is sampled (the phase's last count is always added).
    warmup_*: samples from this count on are judged for flatness (within flat_mb).
    sample_period_s: periodic samples of the pipeline phase. workdir: the node's log and
    stderr (a temporary directory if None, deleted afterwards). core_vocabulary: 0 = the core
    phase uses the bundle's vocabulary, tree and training observations (its mean words per
    image); V > 0 = a random Chow-Liu tree over V words with synthetic observations of
    core_words words (the bundle still gives the rest; a sparser, cheaper index). max_seconds:
    each phase stops there (publishing / observations) if not done, and says so.
    """

    bundle: str
    frames: int = 100_000
    observations: int = 1_000_000
    max_places: int = 2000
    rate_hz: float = 30.0
    window: int = 2
    size: tuple[int, int] = (640, 480)
    jpeg_quality: int = 90
    mcap_max_mb: float = 20.0
    log_budget_mb: float = 100.0
    image_every: int = 1
    queue: int = 2
    frame_checkpoints: tuple[int, ...] = FRAME_CHECKPOINTS
    observation_checkpoints: tuple[int, ...] = OBSERVATION_CHECKPOINTS
    warmup_frames: int = 10_000
    warmup_observations: int = 10_000
    flat_mb: float = 5.0
    sample_period_s: float = 5.0
    node_threads: int | None = 1
    workdir: str | None = None
    core_vocabulary: int = 0
    core_words: int = 300
    max_seconds: float | None = None
    seed: int = 0
    start_timeout_s: float = 90.0
    drain_s: float = 3.0

    def __post_init__(self) -> None:
        if self.frames < 0 or self.observations < 0:
            raise ConfigError("frames and observations must be >= 0")
        if self.frames == 0 and self.observations == 0:
            raise ConfigError("nothing to do: frames and observations are both 0")
        if self.max_places < 1 or self.window < 1 or self.queue < 1:
            raise ConfigError("max_places, window and queue must be >= 1")
        if self.rate_hz < 0:
            raise ConfigError(f"rate must be >= 0 Hz (0: closed loop), got {self.rate_hz}")
        if any(c < 1 for c in (*self.frame_checkpoints, *self.observation_checkpoints)):
            raise ConfigError("checkpoints must be >= 1")
        if self.sample_period_s <= 0 or self.flat_mb <= 0:
            raise ConfigError("sample_period_s and flat_mb must be > 0")
        if self.core_vocabulary < 0 or self.core_words < 1:
            raise ConfigError("core_vocabulary must be >= 0 and core_words >= 1")
        if self.max_seconds is not None and self.max_seconds <= 0:
            raise ConfigError(f"max_seconds must be > 0, got {self.max_seconds}")
        if self.node_threads is not None and self.node_threads < 1:
            raise ConfigError(f"node_threads must be None or >= 1, got {self.node_threads}")


def _checkpoints(points: tuple[int, ...], n: int) -> list[int]:
    """The checkpoints within n, plus n itself, sorted."""
    return sorted({p for p in points if p <= n} | {n})


def flatness(samples: list[dict], count_key: str, warmup: int, flat_mb: float) -> dict:
    """RSS of the samples taken at count_key >= warmup: first/last/min/max, growth (last - first),
    range (max - min) and ``met`` (range <= flat_mb; None with fewer than two samples)."""
    rss = [s["rss_mb"] for s in samples if s[count_key] >= warmup and s["rss_mb"] is not None]
    if len(rss) < 2:
        return {"warmup": warmup, "samples": len(rss), "first": None, "last": None, "min": None, "max": None,
                "growth_mb": None, "range_mb": None, "flat_mb": flat_mb, "met": None}
    return {"warmup": warmup, "samples": len(rss), "first": rss[0], "last": rss[-1], "min": min(rss),
            "max": max(rss), "growth_mb": round(rss[-1] - rss[0], 2), "range_mb": round(max(rss) - min(rss), 2),
            "flat_mb": flat_mb, "met": max(rss) - min(rss) <= flat_mb}


def flatness_at_cap(samples: list[dict], count_key: str, cap: int, flat_mb: float) -> dict:
    """:func:`flatness` from the first sample with the map at its cap (``places`` >= cap) on;
    ``cap_reached_at``: that sample's count (None: never reached)."""
    at = next((s[count_key] for s in samples if (s.get("places") or 0) >= cap), None)
    if at is None:
        return flatness([], count_key, 0, flat_mb) | {"cap_reached_at": None}
    return flatness(samples, count_key, at, flat_mb) | {"cap_reached_at": at}


def _thin(samples: list[dict], keep: int = 200) -> list[dict]:
    return samples[:: max(1, len(samples) // keep)] + ([samples[-1]] if len(samples) > keep else [])


def log_disk_usage(directory: Path) -> dict:
    """MCAP files of a log directory now: count, total and largest bytes."""
    sizes = []
    for p in directory.glob("*.mcap"):
        try:
            sizes.append(p.stat().st_size)
        except OSError:  # deleted by the log budget meanwhile
            continue
    return {"files": len(sizes), "bytes": int(sum(sizes)), "largest_bytes": int(max(sizes, default=0))}


# =============================================================================== pipeline


class _Tally(ResultCollector):
    """Counts the node's results and keeps its last stats."""

    def __init__(self) -> None:
        super().__init__()
        self.places_last: int | None = None
        self.places_max = 0
        self.evictions = 0
        self.loops = 0
        self.latency_ms: list[float] = []  # publish stamp -> result received here
        self.stats: StatsMessage | None = None
        self.n_stats = 0

    def _keep_result(self, res: FrameResult, recv_ns: int) -> None:
        self.places_last = res.n_places
        self.places_max = max(self.places_max, res.n_places or 0)
        self.evictions += res.evicted_place is not None
        self.loops += bool(res.loop)
        if res.stamp_ns:
            self.latency_ms.append((recv_ns - res.stamp_ns) / 1e6)

    def _keep_stats(self, msg: StatsMessage) -> None:
        self.stats, self.n_stats = msg, self.n_stats + 1


class _Probe:
    """One sample of the running node: frames, RSS, places, log set on disk, node drops."""

    def __init__(self, pid: int, logdir: Path, tally: _Tally, t0: float) -> None:
        self.pid, self.logdir, self.tally, self.t0 = pid, logdir, tally, t0
        self.published = 0
        self.lock = threading.Lock()
        self.periodic: list[dict] = []
        self.checkpoints: list[dict] = []

    def sample(self) -> dict:
        rss = process_rss_mb(self.pid)
        disk = log_disk_usage(self.logdir)
        st = self.tally.stats
        return {
            "frames": self.published, "processed": self.tally.processed, "t_s": round(time.monotonic() - self.t0, 1),
            "rss_mb": None if rss is None else round(rss, 2), "places": self.tally.places_last,
            "log_files": disk["files"], "log_bytes": disk["bytes"],
            "node_dropped": st.dropped if st else None, "load_average": load_average(),
        }

    def checkpoint(self) -> None:
        with self.lock:
            self.checkpoints.append(self.sample())

    def run_periodic(self, period_s: float, stop: threading.Event) -> None:
        while not stop.wait(period_s):
            with self.lock:
                self.periodic.append(self.sample())


def _soak_pipeline(cfg: SoakConfig, workdir: Path) -> dict:
    from aefabmap_runtime.adapters.frames import encode_frame
    from aefabmap_runtime.adapters.zenoh_transport import (
        FramePublisher,
        result_key_for,
        stats_key_for,
    )
    from aefabmap_runtime.tools.synthetic_route import random_views

    logdir = workdir / "log"
    logdir.mkdir(parents=True, exist_ok=True)
    views = random_views(cfg.seed, cfg.size)  # renders the world first (docs/results.md, "Streaming")
    key = f"aefabmap/soak/{uuid.uuid4().hex[:8]}/image"
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    extra = ["--max-places", str(cfg.max_places), "--queue", str(cfg.queue), "--image-every", str(cfg.image_every),
             "--mcap-max-mb", str(cfg.mcap_max_mb), "--log-budget-mb", str(cfg.log_budget_mb)]
    load_start = load_average()
    node = start_run_node(cfg.bundle, key, endpoint, f"{logdir}/", workdir / "node.log", extra, cfg.node_threads)
    t0 = time.monotonic()
    tally = _Tally()
    probe = _Probe(node.pid, logdir, tally, t0)
    stop = threading.Event()
    sampler = threading.Thread(target=probe.run_periodic, args=(cfg.sample_period_s, stop), daemon=True)
    checkpoints = set(_checkpoints(cfg.frame_checkpoints, cfg.frames))
    session = pub = None
    stopped_early = False
    lost = 0  # closed loop: frames given up on (no result within 2 s)
    frame_bytes = 0
    t_first = t_last = None
    try:
        session = connect_when_listening(endpoint, node, cfg.start_timeout_s)
        rkey = result_key_for(key)
        subs = [session.declare_subscriber(rkey, tally.on_result),
                session.declare_subscriber(stats_key_for(rkey), tally.on_stats)]
        pub = FramePublisher(session, key, congestion="drop")
        if not pub.wait_for_subscriber(cfg.start_timeout_s):
            raise TransportError(f"the runtime node did not subscribe to {key} within {cfg.start_timeout_s} s")
        sampler.start()
        period = 1.0 / cfg.rate_hz if cfg.rate_hz > 0 else 0.0
        next_t = time.monotonic()
        for i in range(cfg.frames):
            if cfg.max_seconds is not None and time.monotonic() - t0 > cfg.max_seconds:
                stopped_early = True
                break
            payload, enc = encode_frame(next(views), "jpeg", jpeg_quality=cfg.jpeg_quality)
            frame_bytes += len(payload)
            if i == 1 and not tally.wait_processed(1, cfg.start_timeout_s):
                # The first frame pays the node's one-time costs; wait for it before pacing.
                raise TransportError("the runtime node did not answer the first frame")
            if i == 1:
                next_t = time.monotonic()
            if period:
                delay = next_t - time.monotonic()
                if delay > 0:
                    stop.wait(delay)
                next_t = max(next_t + period, time.monotonic() - period)  # behind: no burst to catch up
            else:
                target = i - lost - cfg.window + 1  # results needed before frame i may go out
                while target > 0 and not tally.wait_processed(target, 2.0):
                    lost += 1  # dropped somewhere: do not stall on it
                    target -= 1
            pub.put(payload, enc, stamp_ns=time.time_ns())
            probe.published = i + 1
            t_first = t_first or time.monotonic()
            if i + 1 in checkpoints and i + 1 < cfg.frames:
                probe.checkpoint()
        tally.drain(probe.published, cfg.drain_s, 120.0)
        t_last = time.monotonic()
        probe.checkpoint()  # the last count, after the drain
        for s in subs:
            s.undeclare()
    finally:
        stop.set()
        if pub is not None:
            pub.close()
        if session is not None:
            session.close()
        summary = stop_node(node)
        if sampler.is_alive():
            sampler.join(timeout=10)
    disk_end = log_disk_usage(logdir)
    samples = sorted(probe.checkpoints + probe.periodic, key=lambda s: (s["frames"], s["t_s"]))
    seconds = (t_last - t_first) if t_first and t_last else None
    processed = tally.processed
    sm = summary.to_dict() if summary is not None else None
    if sm is not None:
        sm["log_files"] = sm["log_files"][-5:]  # the last names are enough here
    return {
        "frames_requested": cfg.frames,
        "stopped_at_max_seconds": stopped_early,
        "frames_published": probe.published,
        "frames_processed": processed,
        "not_processed": probe.published - processed,
        "drop_fraction": round(1 - processed / probe.published, 5) if probe.published else None,
        "node_dropped": summary.dropped if summary else None,
        "closed_loop_lost": lost if cfg.rate_hz == 0 else None,
        "mode": f"paced at {cfg.rate_hz:g} Hz" if cfg.rate_hz else f"closed loop, {cfg.window} frames in flight",
        "frame_size": list(cfg.size),
        "frame_source": "synthetic_route.random_views (no two alike), JPEG",
        "mean_frame_bytes": int(frame_bytes / max(1, probe.published)),
        "seconds": round(seconds, 1) if seconds else None,
        "processed_fps": round(processed / seconds, 2) if seconds else None,
        "places": {"last": tally.places_last, "max": tally.places_max},
        "evictions": tally.evictions,
        "loops": tally.loops,
        "latency_ms": _stats(tally.latency_ms),
        "rss_mb_at": {str(s["frames"]): s["rss_mb"] for s in probe.checkpoints},
        "checkpoints": probe.checkpoints,
        "series": _thin(probe.periodic),
        "rss_flat": flatness(samples, "frames", cfg.warmup_frames, cfg.flat_mb),
        "rss_flat_at_cap": flatness_at_cap(samples, "frames", cfg.max_places, cfg.flat_mb),
        "log": {
            "dir_end": disk_end,
            "files_peak": max((s["log_files"] for s in samples), default=0),
            "bytes_peak_sampled": max((s["log_bytes"] for s in samples), default=0),
            "files_deleted": summary.log_files_deleted if summary else None,
            "files_created": (summary.log_files_deleted + disk_end["files"]) if summary else None,
            "errors": summary.log_errors if summary else None,
            "last_state": tally.stats.log_state if tally.stats else None,
        },
        "node_summary": sm,
        "invalid_messages": tally.invalid,
        "load_average_start": load_start,
        "load_average_end": load_average(),
    }


# =============================================================================== core


def _soak_core_here(cfg: SoakConfig) -> dict:
    """The core phase, in this process (see module docstring)."""
    from aefabmap_runtime.adapters.bundle_reader import load_bundle, load_detector
    from aefabmap_runtime.core.detector import DetectorConfig, LoopClosureDetector
    from aefabmap_runtime.tools.synthetic_observations import observation_stream

    dcfg = DetectorConfig(max_places=cfg.max_places, threads=1)
    if cfg.core_vocabulary:
        det = LoopClosureDetector(_SyntheticVocabulary(load_bundle(cfg.bundle), cfg.core_vocabulary,
                                                       cfg.core_words, cfg.seed), dcfg)
        words = cfg.core_words
    else:
        det = load_detector(cfg.bundle, dcfg)
        train = det.bundle.training_observations
        words = max(1, round(float(np.mean([len(o) for o in train])))) if train else cfg.core_words
    vocab = det.bundle.vocabulary_size
    stream = observation_stream(vocab, words, cfg.seed + 17)
    n = cfg.observations
    done = n
    marks = set(_checkpoints(cfg.observation_checkpoints, n))
    every = max(1, n // 200)
    load_start = load_average()
    rss_start = process_rss_mb("self")
    checkpoints, periodic = [], []
    evictions = loops = 0
    t0 = time.monotonic()
    for i in range(1, n + 1):
        if cfg.max_seconds is not None and i % 100 == 0 and time.monotonic() - t0 > cfg.max_seconds:
            done = i - 1
            rss = process_rss_mb("self")
            checkpoints.append({"observations": done, "t_s": round(time.monotonic() - t0, 1),
                                "rss_mb": None if rss is None else round(rss, 2), "places": det.n_places,
                                "map_mb": round(det.map_bytes() / 2**20, 3), "load_average": load_average()})
            break
        res = det.process_words(next(stream).astype(np.int32), stamp_ns=i)
        evictions += res.evicted_place is not None
        loops += bool(res.loop)
        if i in marks or i % every == 0:
            rss = process_rss_mb("self")
            s = {"observations": i, "t_s": round(time.monotonic() - t0, 1),
                 "rss_mb": None if rss is None else round(rss, 2), "places": det.n_places,
                 "map_mb": round(det.map_bytes() / 2**20, 3), "load_average": load_average()}
            (checkpoints if i in marks else periodic).append(s)
    seconds = time.monotonic() - t0
    samples = sorted(checkpoints + periodic, key=lambda s: s["observations"])
    return {
        "observations_requested": n,
        "observations": done,
        "stopped_at_max_seconds": done < n,
        "vocabulary": "synthetic (random Chow-Liu tree)" if cfg.core_vocabulary else "the bundle's",
        "vocabulary_size": int(vocab),
        "words_per_observation": words,
        "entry_point": "LoopClosureDetector.process_words (FAB-MAP 2.0, delayed insertion, LRU eviction)",
        "seconds": round(seconds, 1),
        "observations_per_s": round(done / seconds, 1) if seconds > 0 else None,
        "places": {"last": det.n_places, "id_range": int(det.place_frames().size)},
        "evictions": evictions,
        "loops": loops,
        "map_mb_end": round(det.map_bytes() / 2**20, 3),
        "rss_mb_start": None if rss_start is None else round(rss_start, 2),
        "rss_mb_at": {str(s["observations"]): s["rss_mb"] for s in checkpoints},
        "checkpoints": checkpoints,
        "series": _thin(periodic),
        "rss_flat": flatness(samples, "observations", cfg.warmup_observations, cfg.flat_mb),
        "rss_flat_at_cap": flatness_at_cap(samples, "observations", cfg.max_places, cfg.flat_mb),
        "process": "spawned, OMP/OPENBLAS/MKL_NUM_THREADS=1",
        "load_average_start": load_start,
        "load_average_end": load_average(),
    }


class _SyntheticVocabulary:
    """A model bundle whose vocabulary is replaced by a random Chow-Liu tree over `v` words and
    1000 synthetic training observations of `words` words (core phase only: no quantiser use)."""

    def __init__(self, bundle, v: int, words: int, seed: int) -> None:
        from aefabmap_runtime.tools.synthetic_observations import (
            random_tree,
            synthetic_observations,
        )

        self._bundle = bundle
        self.vocabulary_size = v
        self.tree = random_tree(v, seed)
        self.training_observations = synthetic_observations(1000, v, words, seed + 1)

    def __getattr__(self, name: str):
        return getattr(self._bundle, name)


# =============================================================================== both


def bench_soak(config: SoakConfig) -> dict:
    """Run the selected phases (pipeline first); returns the figures (see module docstring)."""
    if not Path(config.bundle).is_dir():
        raise BundleError(f"model bundle {config.bundle} does not exist")
    out: dict = {"benchmark": "soak", "config": asdict(config), "machine": machine_info(),
                 "pipeline": None, "core": None}
    if config.frames:
        workdir, tmp = bench_workdir(config.workdir, "aefabmap-soak-")
        try:
            out["pipeline"] = _soak_pipeline(config, workdir)
        finally:
            if tmp is not None:
                tmp.cleanup()
    if config.observations:
        out["core"] = run_spawned_single_thread(_soak_core_here, config)
    return out


__all__ = [
    "FRAME_CHECKPOINTS",
    "OBSERVATION_CHECKPOINTS",
    "SoakConfig",
    "bench_soak",
    "flatness",
    "flatness_at_cap",
    "log_disk_usage",
]
