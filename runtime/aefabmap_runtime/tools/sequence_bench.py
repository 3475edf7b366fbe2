"""Per-frame cost of the runtime's own path over a folder of real images (``aefabmap bench sequence``).

Each image is read and decoded, then goes through the frame loop a node runs (runtime/adapters/
frame_loop.py: decode, features, words, FAB-MAP, the candidate policy, verification, insertion), in
file-name order, on one pinned core with one thread everywhere (as ``bench pipeline``). No
evaluation, no ground truth: what a board pays per frame of this sequence. Printed and saved per
stage (wall and CPU ms, median / p95 / mean), with the total and the frames per second; with
`calls`, also the CPU ms per frame spent inside each library's compiled calls (call_profile.py).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path

from aefabmap_runtime.errors import BundleError, ConfigError, InputError
from aefabmap_runtime.core.kernels.compiled import KERNEL_CHOICES
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

    def __post_init__(self) -> None:
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
    return run_benchmark(_bench_here, config)


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
    t_start = time.perf_counter()
    for i, path in enumerate(paths):
        w0, c0 = time.perf_counter(), time.process_time()
        out = loop.step_file(path, i)
        wall_ms, cpu_ms = (time.perf_counter() - w0) * 1e3, (time.process_time() - c0) * 1e3
        stage = {"decode": out.decode_ms, "verification": 0.0, **out.result.timings_ms}
        share = cpu_ms / wall_ms if wall_ms > 0 else 1.0  # CPU shared out by the stages' wall times
        for name in STAGES:
            wall[name].append(stage.get(name, 0.0))
            cpu[name].append(stage.get(name, 0.0) * share)
        total_wall.append(wall_ms)
        total_cpu.append(cpu_ms)
        tried.append(out.result.candidates_tried)
        if image_size is None and out.gray is not None:
            image_size = [int(out.gray.shape[1]), int(out.gray.shape[0])]
    seconds = time.perf_counter() - t_start
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
