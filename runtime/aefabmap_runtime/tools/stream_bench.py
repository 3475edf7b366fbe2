"""Streaming benchmarks: per-stage pipeline cost on one core, and the two-process Zenoh stream.

Pure of argparse (``aefabmap bench pipeline`` / ``aefabmap bench stream`` wrap it); every
function returns a JSON-able dict.

:func:`bench_pipeline` times decode -> features -> quantise -> FAB-MAP inference (->
verification) per frame for 640x480 synthetic frames (runtime/aefabmap_runtime/tools/synthetic_route.py, JPEG)
with a map pre-filled to N places, through the runtime's own frame loop
(runtime/aefabmap_runtime/adapters/frame_loop.py): stage times are the loop's decode time and the detector's
``timings_ms``. It runs in a fresh *spawned* process pinned to one CPU with
``OMP_NUM_THREADS=OPENBLAS_NUM_THREADS=1``, ``cv2.setNumThreads(1)`` and onnxruntime at one
thread, so that numpy's BLAS (the k-means quantiser's product) cannot use a second core.
Pre-filling goes through the detector's public ``process_words`` (delayed insertion, LRU
bookkeeping, the same code as live frames), with word sets of realistic size: by default
the bundle's own training observations cycled (real word statistics of real images, so the
inverted-index postings have realistic lengths), or ``synthetic_observations`` of the
bundle's mean words per image. Wall time (perf_counter) and CPU time (process_time) are
both reported: on a loaded machine wall time includes time the process was not scheduled.
The detector times its stages by wall clock only, so a stage's CPU time is the frame's CPU
time shared out in proportion to the stages' wall times (``stages_cpu_method``).

:func:`bench_stream` starts ``aefabmap run`` as a child process listening on a free
loopback port and drives it from this process (publisher thread + result subscriber on one
Zenoh session), in phases against the same node:

- ``throughput``: closed loop, ``window`` frames in flight: a new frame is published as soon
  as a result comes back, so the node is never idle and nothing is dropped; frames/s.
- ``rate``: fixed rate (30 Hz): end-to-end latency = result receive time - the publisher's
  ``stamp_ns`` attachment (both ``time.time_ns()`` on this machine).
- ``flood``: 200 Hz: frames not processed (dropped by the newest-wins ring) and latency of
  those processed, early vs late half (bounded = does not grow).
- ``soak``: a long run at ``soak_rate_hz`` with the node's ``--max-places`` cap reached early;
  RSS of the node sampled from ``/proc/<pid>/status`` (and its stats messages).
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
import uuid
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from aefabmap_runtime.errors import BundleError, ConfigError, TransportError
from aefabmap_runtime.core.kernels.compiled import KERNEL_CHOICES
from aefabmap_runtime.core.records.messages import FrameResult, StatsMessage
from aefabmap_runtime.tools.node_process import (
    SINGLE_THREAD_ENV,
    ResultCollector,
    bench_workdir,
    connect_when_listening,
    free_tcp_port,
    process_rss_mb,
    start_run_node,
    stop_node,
)


def _stats(values, prefix: str = "") -> dict:
    """median / p95 / mean / max (ms) of a list of numbers; None values when empty."""
    a = np.asarray([v for v in values if v is not None], dtype=np.float64)
    keys = ("median", "p95", "mean", "max")
    if a.size == 0:
        return {f"{prefix}{k}": None for k in keys} | {f"{prefix}n": 0}
    return {
        f"{prefix}median": round(float(np.median(a)), 3),
        f"{prefix}p95": round(float(np.percentile(a, 95)), 3),
        f"{prefix}mean": round(float(a.mean()), 3),
        f"{prefix}max": round(float(a.max()), 3),
        f"{prefix}n": int(a.size),
    }


def load_average() -> list[float] | None:
    """1, 5 and 15 minute load averages (None where unavailable)."""
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:
        return None


def machine_info() -> dict:
    return {"cpus": os.cpu_count(), "load_average": load_average(), "python": sys.version.split()[0]}


def synthetic_frames(n_frames: int, seed: int = 0, jpeg_quality: int = 90) -> list[tuple[bytes, str]]:
    """n_frames 640x480 frames of the synthetic two-lap route, JPEG-encoded once."""
    from aefabmap_runtime.adapters.frames import encode_frame
    from aefabmap_runtime.tools.synthetic_route import generate_loop_sequence

    if n_frames < 4:
        raise ConfigError(f"need at least 4 synthetic frames, got {n_frames}")
    images, _ = generate_loop_sequence(n_frames, seed=seed, size=(640, 480))
    return [encode_frame(img, "jpeg", jpeg_quality=jpeg_quality) for img in images]


# =============================================================================== pipeline

#: Synthetic frames (of another seed) whose keypoints the pre-filled places share.
PLACE_KEYPOINT_FRAMES = 64


@dataclass(frozen=True)
class PipelineBenchConfig:
    """Settings of :func:`bench_pipeline`.

    bundle: model bundle directory. places: places in the map before timing. frames: timed
    frames (after `warmup` untimed ones). prefill: "train" (the bundle's training
    observations, cycled) or "synthetic" (synthetic_observations with the bundle's mean words
    per image). verification: geometric verification on (the runtime's default) or off.
    verify_keypoints: VerificationConfig.keypoints (None: the runtime's default).
    verify_bruteforce: CandidateConfig.bruteforce_fallback, FAB-MAP candidates retried with
    all-pairs matching (None: the runtime's default).
    place_keypoints: pre-filled places carry real keypoints (those of 64 synthetic frames of
    another seed, a world the timed frames never revisit), so every FAB-MAP candidate is
    verified as in a live map, and frames pay what a frame that is not a loop pays. False:
    words only; such places are never verified, which understates verification's cost.
    single_core: spawn a process pinned to one CPU with one thread everywhere.
    scatter: the kernels (runtime/aefabmap_runtime/core/kernels/compiled.py: FAB-MAP's scatter, verification's matching,
    the int8 search's re-rank): "auto" (the preferred compiled form that can run here), "native"
    (ahead-of-time compiled), "numba" (JIT) or "numpy" (numpy / OpenCV fallbacks).
    """

    bundle: str
    places: int = 10_000
    frames: int = 150
    warmup: int = 10
    prefill: str = "train"
    verification: bool = True
    verify_keypoints: int | None = None
    verify_bruteforce: int | None = None
    place_keypoints: bool = True
    scatter: str = "auto"
    seed: int = 0
    single_core: bool = True

    def __post_init__(self) -> None:
        if self.places < 0:
            raise ConfigError(f"places must be >= 0, got {self.places}")
        if self.frames < 1 or self.warmup < 0:
            raise ConfigError("frames must be >= 1 and warmup >= 0")
        if self.prefill not in ("train", "synthetic"):
            raise ConfigError(f"prefill must be 'train' or 'synthetic', got {self.prefill!r}")
        if self.scatter not in KERNEL_CHOICES:
            raise ConfigError(f"scatter must be one of {', '.join(KERNEL_CHOICES)}, got {self.scatter!r}")
        self.detector_config()  # its owners' checks (keypoints, retries), before any loading

    def detector_config(self):
        """The DetectorConfig the benchmark runs (`bench_detector_config`)."""
        return bench_detector_config(verification=self.verification, verify_keypoints=self.verify_keypoints,
                                     verify_bruteforce=self.verify_bruteforce)


def bench_detector_config(*, exclude: int | None = None, verification: bool = True, verify_keypoints: int | None = None,
                          verify_bruteforce: int | None = None, verify_upright: bool | None = None):
    """The DetectorConfig a benchmark runs: one thread, the runtime's defaults but for the settings
    given (None: the default), as `run` sets them with --exclude, --no-verify, --verify-keypoints,
    --verify-bruteforce and --no-verify-upright. ConfigError (the configs' own checks) for bad ones."""
    from aefabmap_runtime.core.detector import DetectorConfig

    d = DetectorConfig()
    v, c = replace(d.verification, enabled=verification), d.candidates
    if verify_keypoints is not None:
        v = replace(v, keypoints=verify_keypoints)
    if verify_upright is not None:
        v = replace(v, upright=verify_upright)
    if verify_bruteforce is not None:
        c = replace(c, bruteforce_fallback=verify_bruteforce)
    return replace(d, threads=1, exclude=d.exclude if exclude is None else exclude, verification=v, candidates=c)


def bench_pipeline(config: PipelineBenchConfig) -> dict:
    """Per-stage ms per frame with a pre-filled map (see module docstring)."""
    if not Path(config.bundle).is_dir():
        raise BundleError(f"model bundle {config.bundle} does not exist")
    return run_benchmark(_bench_pipeline_here, config)


def run_benchmark(fn, config) -> dict:
    """fn(config) in a spawned single-thread process (config.single_core), else here, with the
    choice of compiled kernels (config.scatter, made by fn through `prepare_process`) restored after."""
    if config.single_core:
        return run_spawned_single_thread(fn, config)
    from aefabmap_runtime.core.kernels import compiled

    previous = compiled.backend()
    try:
        return fn(config)
    finally:
        compiled.use(previous)


def prepare_process(config, cores: int = 1) -> int | list[int] | None:
    """Kernels as config.scatter asks (KERNEL_CHOICES; "auto": the preferred compiled form), and with
    config.single_core one OpenCV thread on one pinned CPU; returns that CPU (None: not pinned).
    cores > 1: pinned to that many CPUs instead (the last ones), whose list is returned."""
    import cv2

    from aefabmap_runtime.core.kernels import compiled

    compiled.use(True if config.scatter == "auto" else config.scatter)
    if not config.single_core:
        return None
    cv2.setNumThreads(1)
    return pin_one_cpu() if cores == 1 else pin_cpus(cores)


def run_spawned_single_thread(fn, *args):
    """fn(*args) in a freshly spawned process with OMP/OPENBLAS/MKL_NUM_THREADS=1 set before it
    imports numpy (so BLAS cannot take a second core); returns its result."""
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    saved = {k: os.environ.get(k) for k in SINGLE_THREAD_ENV}
    os.environ.update(SINGLE_THREAD_ENV)  # inherited by the spawned child before it imports numpy
    try:
        with ProcessPoolExecutor(max_workers=1, mp_context=mp.get_context("spawn")) as ex:
            return ex.submit(fn, *args).result()
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def pin_cpus(n: int) -> list[int] | None:
    """Pin this process to the last n CPUs it may run on (all of them when fewer); their numbers."""
    try:
        cpus = sorted(os.sched_getaffinity(0))[-n:]
        os.sched_setaffinity(0, set(cpus))
        return cpus
    except (AttributeError, OSError):
        return None


def pin_one_cpu() -> int | None:
    """Pin this process to the last CPU it may run on; that CPU's number (None: not supported)."""
    try:
        cpus = sorted(os.sched_getaffinity(0))
        os.sched_setaffinity(0, {cpus[-1]})
        return cpus[-1]
    except (AttributeError, OSError):
        return None


def _bench_pipeline_here(config: PipelineBenchConfig) -> dict:
    import cv2

    from aefabmap_runtime.adapters.bundle_reader import load_detector
    from aefabmap_runtime.adapters.frame_loop import FrameLoop
    from aefabmap_runtime.adapters.frames import decode_frame
    from aefabmap_runtime.core.kernels import compiled
    from aefabmap_runtime.tools.synthetic_observations import synthetic_observations

    pinned = prepare_process(config)
    det = load_detector(config.bundle, config.detector_config())
    manifest = det.manifest
    vocab = det.bundle.vocabulary_size
    train = det.bundle.training_observations
    mean_words = float(np.mean([len(o) for o in train])) if train else 0.0

    # ---- pre-fill through the detector's public per-frame entry point (words only)
    t0 = time.perf_counter()
    if config.prefill == "train":
        sets = [train[i % len(train)] for i in range(config.places)]
    else:
        sets = synthetic_observations(config.places, vocab, max(1, round(mean_words)), config.seed + 11)
    for i, words in enumerate(sets):
        det.process_words(np.asarray(words, dtype=np.int32), stamp_ns=i)
    del sets
    if config.place_keypoints and config.verification:
        pool = [det.extractor.extract(decode_frame(payload, enc))
                for payload, enc in synthetic_frames(PLACE_KEYPOINT_FRAMES, seed=config.seed + 101)]
        pool = [(f, det.words_of(f)) for f in pool]
        for pid in np.flatnonzero(det.scorer.alive).tolist():
            det.attach_keypoints(pid, *pool[pid % len(pool)])
    prefill_s = time.perf_counter() - t0

    frames = synthetic_frames(max(4, config.frames + config.warmup), seed=config.seed)
    names = ("decode", "features", "quantise", "inference", "verification")
    stages: dict[str, list[float]] = {k: [] for k in names}
    stages_cpu: dict[str, list[float]] = {k: [] for k in names}
    total_wall, total_cpu, total_wo_verif = [], [], []
    n_places, n_words, n_kps, tried, loops = [], [], [], [], 0
    loop = FrameLoop(det, strict=True)  # the runtime's own per-frame step; a bad frame is a bug here
    for i, (payload, enc) in enumerate(frames[: config.frames + config.warmup]):
        w0, c0 = time.perf_counter(), time.process_time()
        out = loop.step(payload, enc, config.places + i)
        wall_ms, cpu_ms = (time.perf_counter() - w0) * 1e3, (time.process_time() - c0) * 1e3
        if i < config.warmup:
            continue
        res = out.result
        # Stage times are the frame loop's decode time and the detector's own timings_ms (wall).
        wall = {"decode": out.decode_ms, "verification": 0.0, **res.timings_ms}
        # CPU per stage: the step's CPU time shared out in proportion to the stages' wall times
        # (one pinned thread: CPU ~ wall unless the process was descheduled).
        share = cpu_ms / wall_ms if wall_ms > 0 else 1.0
        for name in names:
            stages[name].append(wall.get(name, 0.0))
            stages_cpu[name].append(wall.get(name, 0.0) * share)
        total_wall.append(wall_ms)
        total_cpu.append(cpu_ms)
        total_wo_verif.append(wall_ms - wall["verification"])
        n_places.append(res.n_places)
        n_words.append(res.n_words)
        n_kps.append(res.n_keypoints)
        tried.append(res.candidates_tried)
        loops += int(bool(res.loop))
    out = {
        "benchmark": "pipeline",
        "bundle": str(config.bundle),
        "vocabulary_size": vocab,
        "features": manifest.get("features"),
        "quantizer": manifest.get("quantizer", {}).get("type"),
        "frame_size": [640, 480],
        "places_prefilled": config.places,
        "prefill": config.prefill,
        "prefill_words_per_place": round(mean_words, 1),
        "place_keypoints": bool(config.place_keypoints and config.verification),
        "scatter": compiled.backend(),
        "prefill_seconds": round(prefill_s, 2),
        "places_in_map": {"min": int(min(n_places)), "max": int(max(n_places))},
        "map_bytes": int(det.map_bytes()),
        "verification": config.verification,
        "verify_keypoints": det.config.verification.keypoints,
        "verify_bruteforce": det.config.candidates.bruteforce_fallback,
        "frames_timed": len(total_wall),
        "warmup_frames": config.warmup,
        "keypoints_median": float(np.median(n_kps)),
        "places_verified_per_frame": _stats(tried),
        "words_median": float(np.median(n_words)),
        "loops": loops,
        "single_core": config.single_core,
        "pinned_cpu": pinned,
        "threads_env": {k: os.environ.get(k) for k in SINGLE_THREAD_ENV},
        "cv2_threads": cv2.getNumThreads(),
        "stages_ms": {k: _stats(v) for k, v in stages.items()},
        "stages_cpu_ms": {k: _stats(v) for k, v in stages_cpu.items()},
        "stages_cpu_method": "frame CPU time (process_time) shared out by the stages' wall times",
        "total_ms": _stats(total_wall),
        "total_cpu_ms": _stats(total_cpu),
        "total_without_verification_ms": _stats(total_wo_verif),
        "machine": machine_info(),
    }
    med = out["total_ms"]["median"]
    out["target"] = {
        "median_total_ms_le": 10.0,
        "met_wall": med is not None and med <= 10.0,
        "met_cpu": out["total_cpu_ms"]["median"] is not None and out["total_cpu_ms"]["median"] <= 10.0,
    }
    return out


# =============================================================================== stream


@dataclass(frozen=True)
class StreamBenchConfig:
    """Settings of :func:`bench_stream`. Times in seconds, rates in Hz.

    bundle: model bundle for the node. rate_hz / seconds: the fixed-rate latency phase.
    throughput_seconds / window: closed-loop phase (frames in flight). flood_hz /
    flood_seconds: the flood phase. soak_seconds / soak_rate_hz: the RSS phase (0 = skip).
    max_places: the node's --max-places (small, so the cap is reached early). queue: the
    node's --queue. image_every: the node's --image-every. n_frames: distinct synthetic frames
    (cycled). workdir: where the node's MCAP log goes (a temporary directory if None).
    start_timeout_s: wait for the node to start. drain_s: idle time that ends a phase's drain.
    node_threads: OMP_NUM_THREADS / OPENBLAS_NUM_THREADS of the node process (1, as
    deploy/aefabmap.service sets it); None inherits this process's environment (numpy's BLAS
    then starts one thread per core, which an oversubscribed machine punishes).
    """

    bundle: str
    rate_hz: float = 30.0
    seconds: float = 15.0
    throughput_seconds: float = 15.0
    window: int = 2
    flood_hz: float = 200.0
    flood_seconds: float = 10.0
    soak_seconds: float = 60.0
    soak_rate_hz: float = 30.0
    max_places: int = 100
    memory_mb: float | None = None
    queue: int = 2
    image_every: int = 1
    n_frames: int = 160
    seed: int = 0
    rss_period_s: float = 0.5
    start_timeout_s: float = 60.0
    drain_s: float = 1.0
    workdir: str | None = None
    keep_log: bool = False
    node_threads: int | None = 1

    def __post_init__(self) -> None:
        if self.node_threads is not None and self.node_threads < 1:
            raise ConfigError(f"node_threads must be None or >= 1, got {self.node_threads}")
        for name in ("rate_hz", "flood_hz", "soak_rate_hz", "rss_period_s", "start_timeout_s", "drain_s"):
            if getattr(self, name) <= 0:
                raise ConfigError(f"{name} must be > 0, got {getattr(self, name)!r}")
        for name in ("seconds", "throughput_seconds", "flood_seconds", "soak_seconds"):
            if getattr(self, name) < 0:
                raise ConfigError(f"{name} must be >= 0, got {getattr(self, name)!r}")
        if self.window < 1 or self.queue < 1 or self.max_places < 1:
            raise ConfigError("window, queue and max_places must be >= 1")


class _Results(ResultCollector):
    """Keeps every result (as a record) and stats message of the node."""

    def __init__(self) -> None:
        super().__init__()
        self.results: list[dict] = []  # {"recv_ns", "stamp_ns", "frame_seq", "n_places", "node_ms", ...}
        self.stats: list[StatsMessage] = []

    def _keep_result(self, res: FrameResult, recv_ns: int) -> None:
        self.results.append({
            "recv_ns": recv_ns,
            "recv_mono": time.monotonic(),
            "stamp_ns": res.stamp_ns,
            "frame_seq": res.frame_seq,
            "n_places": res.n_places,
            "node_ms": res.latency_ms,
            "timings_ms": res.timings_ms,
            "loop": res.loop,
        })

    def _keep_stats(self, msg: StatsMessage) -> None:
        self.stats.append(msg)

    def window(self, t0_ns: int, t1_ns: int) -> list[dict]:
        with self.cond:
            return [r for r in self.results if r["stamp_ns"] is not None and t0_ns <= r["stamp_ns"] <= t1_ns]


class _RssSampler(threading.Thread):
    def __init__(self, pid: int, period_s: float, t0: float) -> None:
        super().__init__(daemon=True, name="rss-sampler")
        self.pid, self.period_s, self.t0 = pid, period_s, t0
        self.samples: list[tuple[float, float]] = []
        self.stop = threading.Event()

    def run(self) -> None:
        while not self.stop.is_set():
            rss = process_rss_mb(self.pid)
            if rss is not None:
                self.samples.append((round(time.monotonic() - self.t0, 3), round(rss, 2)))
            self.stop.wait(self.period_s)

    def between(self, a: float, b: float) -> list[float]:
        return [r for t, r in self.samples if a <= t <= b]


def _start_node(cfg: StreamBenchConfig, key: str, endpoint: str, mcap: Path, stderr_path: Path) -> subprocess.Popen:
    extra = ["--queue", str(cfg.queue), "--max-places", str(cfg.max_places), "--image-every", str(cfg.image_every)]
    if cfg.memory_mb is not None:
        extra += ["--memory-mb", str(cfg.memory_mb)]
    return start_run_node(cfg.bundle, key, endpoint, mcap, stderr_path, extra, cfg.node_threads)


def _latency_summary(recs: list[dict]) -> dict:
    """End-to-end latency (publish stamp -> result received here), the node's own share
    (frame taken from its ring -> result published) and its per-stage timings (medians, ms)."""
    lat = [(r["recv_ns"] - r["stamp_ns"]) / 1e6 for r in recs]
    stages = sorted({k for r in recs for k in r["timings_ms"]})
    return _stats(lat) | {
        "node_ms": _stats([r["node_ms"] for r in recs]),
        "node_stage_median_ms": {k: round(float(np.median([r["timings_ms"].get(k, 0.0) for r in recs])), 3)
                                 for k in stages},
        "loops": sum(r["loop"] for r in recs),
    }


class _Phase:
    """Publishes frames for one phase (its own FramePublisher: its own src and seq from 0)."""

    def __init__(self, session, key: str, frames: list[tuple[bytes, str]]) -> None:
        from aefabmap_runtime.adapters.zenoh_transport import FramePublisher

        self.pub = FramePublisher(session, key, congestion="drop")
        self.pub.wait_for_subscriber(5.0)
        self.frames = frames
        self.published = 0
        self.stop = threading.Event()

    def put(self) -> int:
        payload, enc = self.frames[self.published % len(self.frames)]
        self.pub.put(payload, enc, stamp_ns=time.time_ns())
        self.published += 1
        return self.published

    def paced(self, rate_hz: float, seconds: float) -> float:
        """Publish at rate_hz for `seconds`; returns the achieved duration."""
        period = 1.0 / rate_hz
        t0 = time.monotonic()
        end = t0 + seconds
        next_t = t0
        while not self.stop.is_set():
            now = time.monotonic()
            if now >= end:
                break
            if next_t > now and self.stop.wait(next_t - now):
                break
            self.put()
            next_t += period
            if next_t < time.monotonic() - period:  # fell behind: do not burst to catch up
                next_t = time.monotonic()
        return time.monotonic() - t0

    def close(self) -> None:
        self.pub.close()


def bench_stream(config: StreamBenchConfig) -> dict:
    """Run the phases against one node subprocess; returns the figures (see module docstring)."""
    from aefabmap_runtime.adapters.zenoh_transport import result_key_for, stats_key_for

    if not Path(config.bundle).is_dir():
        raise BundleError(f"model bundle {config.bundle} does not exist")
    workdir, tmp = bench_workdir(config.workdir, "aefabmap-bench-")
    frames = synthetic_frames(config.n_frames, seed=config.seed)
    key = f"aefabmap/bench/{uuid.uuid4().hex[:8]}/image"
    rkey = result_key_for(key)
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    mcap = workdir / "bench_stream.mcap"
    load_start = load_average()
    t_start = time.monotonic()
    node = _start_node(config, key, endpoint, mcap, workdir / "node.log")
    sampler = _RssSampler(node.pid, config.rss_period_s, t_start)
    sampler.start()
    coll = _Results()
    session = None
    phases: dict[str, dict] = {}
    summary = None
    try:
        session = connect_when_listening(endpoint, node, config.start_timeout_s)
        subs = [session.declare_subscriber(rkey, coll.on_result),
                session.declare_subscriber(stats_key_for(rkey), coll.on_stats)]
        # Warm-up: the node loads the bundle after it listens; wait for its subscriber, then
        # for a few results (first frames pay one-time costs).
        warm = _Phase(session, key, frames)
        if not warm.pub.wait_for_subscriber(config.start_timeout_s):
            raise TransportError(f"the runtime node did not subscribe to {key} within {config.start_timeout_s} s")
        for _ in range(5):
            n = warm.put()
            if not coll.wait_processed(n, config.start_timeout_s):
                raise TransportError("the runtime node did not answer the warm-up frames")
        warm.close()
        if config.throughput_seconds > 0:
            phases["throughput"] = _phase_closed_loop(session, key, frames, coll, config, t_start, sampler)
        if config.seconds > 0:
            phases["rate"] = _phase_paced(session, key, frames, coll, config, t_start, sampler,
                                          config.rate_hz, config.seconds)
        if config.flood_seconds > 0:
            phases["flood"] = _phase_paced(session, key, frames, coll, config, t_start, sampler,
                                           config.flood_hz, config.flood_seconds)
        if config.soak_seconds > 0:
            phases["soak"] = _phase_paced(session, key, frames, coll, config, t_start, sampler,
                                          config.soak_rate_hz, config.soak_seconds)
        for s in subs:
            s.undeclare()
    finally:
        if session is not None:
            session.close()
        summary = stop_node(node)
        sampler.stop.set()
        sampler.join(timeout=5)
        if summary is not None:  # the file actually written (a kept workdir's old log is never overwritten)
            mcap = Path(summary.mcap_path)
        mcap_bytes = mcap.stat().st_size if mcap.exists() else None
        if tmp is not None and not config.keep_log:
            tmp.cleanup()
    rss_all = [r for _, r in sampler.samples]
    out = {
        "benchmark": "stream",
        "config": asdict(config),
        "transport": {"endpoint": "tcp/127.0.0.1 (loopback)", "mode": "peer", "multicast_scouting": False},
        "processes": "bench (publisher thread + result subscriber) and `aefabmap run` child",
        "node_threads_env": None if config.node_threads is None else {k: str(config.node_threads) for k in SINGLE_THREAD_ENV},
        "frames": {"size": [640, 480], "encoding": "image/jpeg", "distinct": len(frames),
                   "mean_bytes": int(np.mean([len(p) for p, _ in frames]))},
        "phases": phases,
        "rss_mb": {
            "samples": len(rss_all),
            "first": rss_all[0] if rss_all else None,
            "last": rss_all[-1] if rss_all else None,
            "max": max(rss_all) if rss_all else None,
            "series": sampler.samples[:: max(1, len(sampler.samples) // 120)],
        },
        "node_stats_rss_mb": [s.rss_mb for s in coll.stats],
        "node_summary": summary.to_dict() if summary is not None else None,
        "invalid_messages": coll.invalid,
        "mcap_bytes": mcap_bytes,
        "load_average_start": load_start,
        "machine": machine_info(),
    }
    out["targets"] = _targets(phases)
    return out


def _phase_closed_loop(session, key, frames, coll: _Results, cfg: StreamBenchConfig, t_start, sampler) -> dict:
    ph = _Phase(session, key, frames)
    base = coll.count()
    t0_ns = time.time_ns()
    t0 = time.monotonic()
    end = t0 + cfg.throughput_seconds
    lost = 0
    while time.monotonic() < end:
        # Keep `window` frames in flight: publish when fewer than window are unanswered.
        target = ph.published - lost - cfg.window + 1
        if target > 0 and not coll.wait_processed(base + target, 2.0):
            lost += 1  # a frame went missing (dropped): do not stall on it
            continue
        ph.put()
    coll.drain(base + ph.published - lost, cfg.drain_s, 30.0)
    t1_ns = time.time_ns()
    recs = coll.window(t0_ns, t1_ns)
    duration = (max(r["recv_ns"] for r in recs) - t0_ns) / 1e9 if recs else time.monotonic() - t0
    ph.close()
    return {
        "mode": f"closed loop, {cfg.window} frames in flight",
        "seconds": round(duration, 3),
        "published": ph.published,
        "processed": len(recs),
        "not_processed": ph.published - len(recs),
        "fps": round(len(recs) / duration, 2) if duration > 0 else None,
        "latency_ms": _latency_summary(recs),
        "rss_mb": _stats(sampler.between(t0 - t_start, time.monotonic() - t_start)),
        "load_average": load_average(),
    }


def _phase_paced(session, key, frames, coll: _Results, cfg: StreamBenchConfig, t_start, sampler,
                 rate_hz: float, seconds: float) -> dict:
    ph = _Phase(session, key, frames)
    base = coll.count()
    t0_ns = time.time_ns()
    t0 = time.monotonic()
    dur = ph.paced(rate_hz, seconds)
    coll.drain(base + ph.published, cfg.drain_s, 30.0)
    t1_ns = time.time_ns()
    t1 = time.monotonic()
    recs = coll.window(t0_ns, t1_ns)
    ph.close()
    half = t0_ns + int(dur * 1e9 / 2)
    early = [r for r in recs if r["stamp_ns"] < half]
    late = [r for r in recs if r["stamp_ns"] >= half]
    places = [r["n_places"] for r in recs if r["n_places"] is not None]
    rss = sampler.between(t0 - t_start, t1 - t_start)
    # RSS once the map is full: from `settle_s` after the first result at the cap.
    at_cap = [r["recv_mono"] for r in recs if r["n_places"] is not None and r["n_places"] >= cfg.max_places]
    settle_s = 5.0
    cap_rss = sampler.between(at_cap[0] - t_start + settle_s, t1 - t_start) if at_cap else []
    cap_span = (t1 - at_cap[0] - settle_s) if at_cap else 0.0
    span = (max(r["recv_ns"] for r in recs) - t0_ns) / 1e9 if recs else dur
    return {
        "mode": f"paced at {rate_hz:g} Hz",
        "seconds": round(dur, 3),
        "published": ph.published,
        "publish_rate_hz": round(ph.published / dur, 2) if dur > 0 else None,
        "processed": len(recs),
        "not_processed": ph.published - len(recs),
        "drop_fraction": round(1 - len(recs) / ph.published, 4) if ph.published else None,
        "processed_fps": round(len(recs) / span, 2) if span > 0 else None,
        "latency_ms": _latency_summary(recs),
        "latency_ms_first_half": _stats([(r["recv_ns"] - r["stamp_ns"]) / 1e6 for r in early]),
        "latency_ms_second_half": _stats([(r["recv_ns"] - r["stamp_ns"]) / 1e6 for r in late]),
        "places": {"first": places[0] if places else None, "last": places[-1] if places else None,
                   "max": max(places) if places else None},
        "rss_mb": {"first": rss[0] if rss else None, "last": rss[-1] if rss else None,
                   "max": max(rss) if rss else None, "min": min(rss) if rss else None, "samples": len(rss)},
        "rss_mb_at_cap": {
            "seconds": round(cap_span, 1) if cap_rss else 0.0,
            "first": cap_rss[0] if cap_rss else None, "last": cap_rss[-1] if cap_rss else None,
            "max": max(cap_rss) if cap_rss else None, "samples": len(cap_rss),
            "growth_mb": round(cap_rss[-1] - cap_rss[0], 2) if cap_rss else None,
            "growth_mb_per_hour": round((cap_rss[-1] - cap_rss[0]) / cap_span * 3600, 1)
            if cap_rss and cap_span > 0 else None,
        },
        "load_average": load_average(),
    }


def _targets(phases: dict) -> dict:
    t = {}
    if "throughput" in phases:
        fps = phases["throughput"]["fps"]
        t["sustained_fps_ge_50"] = {"value": fps, "met": fps is not None and fps >= 50}
    if "rate" in phases:
        p95 = phases["rate"]["latency_ms"]["p95"]
        t["p95_latency_ms_le_30_at_30hz"] = {"value": p95, "met": p95 is not None and p95 <= 30}
    if "flood" in phases:
        f = phases["flood"]
        a, b = f["latency_ms_first_half"]["p95"], f["latency_ms_second_half"]["p95"]
        t["flood_latency_bounded"] = {
            "p95_first_half": a, "p95_second_half": b, "not_processed": f["not_processed"],
            "met": a is not None and b is not None and b <= max(2 * a, a + 50),
        }
    if "soak" in phases:
        r = phases["soak"]["rss_mb_at_cap"]
        growth = r["growth_mb"]
        # Flat: less than 2 MB over the run at the cap (allocator noise); None = the cap was never reached.
        t["rss_flat_at_cap"] = {"seconds": r["seconds"], "first": r["first"], "last": r["last"], "max": r["max"],
                                "growth_mb": growth, "growth_mb_per_hour": r["growth_mb_per_hour"],
                                "met": growth is not None and growth <= 2.0}
    return t


__all__ = [
    "PipelineBenchConfig",
    "StreamBenchConfig",
    "bench_pipeline",
    "bench_stream",
    "process_rss_mb",
    "run_spawned_single_thread",
    "synthetic_frames",
]
