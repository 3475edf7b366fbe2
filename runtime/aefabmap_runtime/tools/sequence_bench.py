"""Per-frame cost of the runtime's own path over a folder of real images (``aefabmap bench sequence``).

Each image is read and decoded, then goes through the frame loop a node runs (runtime/adapters/
frame_loop.py: decode, features, words, FAB-MAP, the candidate policy, verification, insertion), in
file-name order, on one pinned core with one thread everywhere (as ``bench pipeline``). No
evaluation, no ground truth: what a board pays per frame of this sequence. Printed and saved per
stage (wall and CPU ms, median / p95 / mean), with the total and the frames per second; with
`calls`, also the CPU ms per frame spent inside each library's compiled calls (call_profile.py).
With `workers` N > 1, a second run goes over the same images with N threads working on frames
(runtime/aefabmap_runtime/adapters/frame_pipeline.py) on N pinned cores: its CPU ms per frame, frames per
second and per-stage wall ms beside the one-thread run's (`workers` in the document).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path

from aefabmap_runtime.errors import BundleError, ConfigError, InputError
from aefabmap_runtime.core.kernels.compiled import KERNEL_CHOICES
from aefabmap_runtime.core.run_config import check_workers
from aefabmap_runtime.tools.stream_bench import (
    SINGLE_THREAD_ENV,
    _stats,
    bench_detector_config,
    machine_info,
    prepare_process,
    run_benchmark,
)

STAGES = ("decode", "features", "quantise", "inference", "verification")


@dataclass(frozen=True)
class SequenceBenchConfig:
    """Settings of :func:`bench_sequence`.

    images: folder of images (list_images: file-name order). bundle: model bundle directory.
    exclude: DetectorConfig.exclude (frames, the sequence's exclusion window). limit: first N images
    only (None: all). scatter: the kernels, as StreamBenchConfig.scatter. single_core: a spawned process pinned to one CPU with one thread everywhere.
    calls: after the timed pass, a second pass from an empty map under the profiler, for the time
    inside each library's calls (`call_profile.GROUPS`; the rest is Python and numpy).
    verify_keypoints / verify_bruteforce / verify_upright: VerificationConfig.keypoints,
    CandidateConfig.bruteforce_fallback and VerificationConfig.upright (None: the runtime's), as
    `run` and `eval` set them with --verify-keypoints, --verify-bruteforce and --no-verify-upright.
    workers: above 1, a second run with that many threads on as many cores (module docstring).
    """

    images: str
    bundle: str
    exclude: int = 50
    limit: int | None = None
    scatter: str = "auto"
    single_core: bool = True
    calls: bool = False
    verify_keypoints: int | None = None
    verify_bruteforce: int | None = None
    verify_upright: bool | None = None
    workers: int = 1

    def __post_init__(self) -> None:
        check_workers(self.workers)
        if self.limit is not None and self.limit < 1:
            raise ConfigError(f"limit must be >= 1 images, got {self.limit}")
        if self.scatter not in KERNEL_CHOICES:
            raise ConfigError(f"scatter must be one of {', '.join(KERNEL_CHOICES)}, got {self.scatter!r}")
        self.detector_config()  # its owners' checks (exclude, keypoints, retries), before any loading

    def detector_config(self):
        """The DetectorConfig both passes run (`stream_bench.bench_detector_config`)."""
        return bench_detector_config(exclude=self.exclude, verify_keypoints=self.verify_keypoints,
                                     verify_bruteforce=self.verify_bruteforce, verify_upright=self.verify_upright)


def bench_sequence(config: SequenceBenchConfig) -> dict:
    """Per-stage ms per frame of the runtime's path over config.images (module docstring)."""
    if not Path(config.bundle).is_dir():
        raise BundleError(f"model bundle {config.bundle} does not exist")
    if not Path(config.images).is_dir():
        raise InputError(f"image folder {config.images} does not exist")
    doc = run_benchmark(_bench_here, config)
    doc["workers"] = {"1": _summary(doc)}
    if config.workers > 1:
        doc["workers"][str(config.workers)] = run_benchmark(_bench_workers_here, config)
    return doc


def _stage_ms(out) -> dict[str, float]:
    """One frame's ms per stage (STAGES; verification 0 where none ran)."""
    return {"decode": out.decode_ms, "verification": 0.0, **out.result.timings_ms}


def _summary(doc: dict) -> dict:
    """The figures compared across worker counts, from a one-thread run's document."""
    return {"cpu_ms_per_frame": doc["cpu_ms_per_frame"], "frames_per_second": doc["frames_per_second"],
            "wall_s": doc["wall_s"], "stages_ms_mean": {k: v["mean"] for k, v in doc["stages_ms"].items()},
            "loops": doc["loops"], "cores": 1 if doc["single_core"] else None}


def _bench_workers_here(config: SequenceBenchConfig) -> dict:
    """The images decided with config.workers threads on as many pinned cores: CPU ms per frame
    (the process's), frames per second and the stages' mean wall ms per frame."""
    from aefabmap_runtime.adapters.bundle_reader import load_detector
    from aefabmap_runtime.adapters.frame_loop import FrameLoop
    from aefabmap_runtime.adapters.frame_pipeline import pipelined
    from aefabmap_runtime.adapters.image_folder import list_images

    cores = prepare_process(config, cores=config.workers)
    paths = list_images(config.images)[: config.limit]
    loop = FrameLoop(load_detector(config.bundle, config.detector_config()), strict=True)
    stages: dict[str, list[float]] = {k: [] for k in STAGES}
    w0, c0 = time.perf_counter(), time.process_time()
    for _, out in pipelined(loop, ((i, p, i) for i, p in enumerate(paths)), config.workers):
        stage = _stage_ms(out)
        for name in STAGES:
            stages[name].append(stage.get(name, 0.0))
    wall, cpu = time.perf_counter() - w0, time.process_time() - c0
    return {"cpu_ms_per_frame": round(cpu * 1e3 / len(paths), 3), "frames_per_second": round(len(paths) / wall, 2),
            "wall_s": round(wall, 3), "stages_ms_mean": {k: _stats(v)["mean"] for k, v in stages.items()},
            "loops": loop.loops, "cores": cores}


def _bench_here(config: SequenceBenchConfig) -> dict:
    from aefabmap_runtime.adapters.bundle_reader import load_detector
    from aefabmap_runtime.adapters.frame_loop import FrameLoop
    from aefabmap_runtime.adapters.image_folder import list_images
    from aefabmap_runtime.core.kernels import compiled

    pinned = prepare_process(config)
    paths = list_images(config.images)[: config.limit]
    if not paths:
        raise InputError(f"no images in {config.images}")
    det = load_detector(config.bundle, config.detector_config())
    loop = FrameLoop(det, strict=True)
    wall: dict[str, list[float]] = {k: [] for k in STAGES}
    cpu: dict[str, list[float]] = {k: [] for k in STAGES}
    total_wall, total_cpu, tried = [], [], []
    image_size = None
    t_start, c_start = time.perf_counter(), time.process_time()
    for i, path in enumerate(paths):
        w0, c0 = time.perf_counter(), time.process_time()
        out = loop.step_file(path, i)
        wall_ms, cpu_ms = (time.perf_counter() - w0) * 1e3, (time.process_time() - c0) * 1e3
        stage = _stage_ms(out)
        share = cpu_ms / wall_ms if wall_ms > 0 else 1.0  # CPU shared out by the stages' wall times
        for name in STAGES:
            wall[name].append(stage.get(name, 0.0))
            cpu[name].append(stage.get(name, 0.0) * share)
        total_wall.append(wall_ms)
        total_cpu.append(cpu_ms)
        tried.append(out.result.candidates_tried)
        if image_size is None and out.gray is not None:
            image_size = [int(out.gray.shape[1]), int(out.gray.shape[0])]
    seconds, cpu_seconds = time.perf_counter() - t_start, time.process_time() - c_start
    manifest = det.manifest
    doc = {
        "benchmark": "sequence",
        "images": str(config.images),
        "bundle": str(config.bundle),
        "vocabulary_size": det.bundle.vocabulary_size,
        "features": manifest.get("features"),
        "exclude": config.exclude,
        "verify_keypoints": det.config.verification.keypoints,
        "verify_bruteforce": det.config.candidates.bruteforce_fallback,
        "verify_upright": det.config.verification.upright,
        "frames": len(paths),
        "image_size_wh": image_size,
        "loops": loop.loops,
        "places": det.n_places,
        "places_verified_per_frame": _stats(tried),
        "scatter": compiled.backend(),
        "single_core": config.single_core,
        "pinned_cpu": pinned,
        "threads_env": {k: os.environ.get(k) for k in SINGLE_THREAD_ENV},
        "stages_ms": {k: _stats(v) for k, v in wall.items()},
        "stages_cpu_ms": {k: _stats(v) for k, v in cpu.items()},
        "total_ms": _stats(total_wall),
        "total_cpu_ms": _stats(total_cpu),
        "frames_per_second": round(len(paths) / seconds, 2) if seconds > 0 else None,
        "wall_s": round(seconds, 3),
        "cpu_ms_per_frame": round(cpu_seconds * 1e3 / len(paths), 3),
        "machine": machine_info(),
    }
    if config.calls:
        doc["calls_cpu_ms_per_frame"] = _calls_per_frame(config, paths, sum(total_cpu) / len(paths))
    return doc


def _calls_per_frame(config: SequenceBenchConfig, paths: list, cpu_ms_per_frame: float) -> dict[str, float]:
    """Mean CPU ms per frame inside each library's calls over a second pass from an empty map, and
    "rest": the timed pass's mean CPU ms per frame beyond them (Python and numpy)."""
    from aefabmap_runtime.adapters.bundle_reader import load_detector
    from aefabmap_runtime.adapters.frame_loop import FrameLoop
    from aefabmap_runtime.tools.call_profile import seconds_in_calls

    loop = FrameLoop(load_detector(config.bundle, config.detector_config()), strict=True)

    def run() -> None:
        for i, path in enumerate(paths):
            loop.step_file(path, i)

    per_frame = {k: round(v * 1e3 / len(paths), 3) for k, v in seconds_in_calls(run).items()}
    per_frame["rest"] = round(cpu_ms_per_frame - sum(per_frame.values()), 3)
    return per_frame
