"""Snapshot cost of the map (``--state DIR``): time and size at a given number of places.

A detector on a bundle gets ``places`` synthetic places (word sets from
synthetic_observations, ``keypoints`` ORB keypoints each with random positions and
descriptors, as verification stores them), then the map is saved to a fresh state directory
(runtime/aefabmap_runtime/adapters/state_dir.py: write + fsync + rename), loaded back and checked.

    python -m aefabmap_runtime.tools.state_bench --model BUNDLE --places 1000 10000

One core; prints one JSON line per size: state_s (arrays gathered), save_s, load_s
(read, checksums, core checks, rebuild) as wall time and *_cpu_s as this process's CPU time
(on a shared machine the wall time also holds the waits for a core), the 1-min load average,
bytes on disk, bytes per place, map_bytes in memory.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time

import numpy as np

from aefabmap_runtime.adapters.bundle_reader import load_detector
from aefabmap_runtime.adapters.state_dir import MapStateDir, bundle_id, load_into
from aefabmap_runtime.core.detector import DetectorConfig
from aefabmap_runtime.tools.synthetic_observations import synthetic_observations


def fill_map(detector, places: int, keypoints: int, seed: int = 0) -> None:
    """Add ``places`` synthetic places straight to the detector's map (no queries: only the map's
    contents matter to a snapshot), one per frame, each with ``keypoints`` stored keypoints."""
    rng = np.random.default_rng(seed)
    own = detector.map
    v = own.vocabulary_size
    obs = synthetic_observations(places, v, min(300, v // 2), seed)
    h, w = 480, 640
    for words in obs:
        kw = rng.choice(words, keypoints) if keypoints else np.zeros(0, np.int64)
        kps = None
        if own.store is not None and keypoints:
            xy = rng.random((keypoints, 2)).astype(np.float32) * [w, h]
            desc = rng.integers(0, 256, (keypoints, own.store.kind.store_bytes), dtype=np.uint8)
            # Upright descriptors where the detector extracts them (VerificationConfig.upright).
            upright = desc[::-1].copy() if detector.config.verification.upright else None
            kps = own.store.pack(xy, kw, desc, (h, w), upright)
        frame, _ = own.begin_frame()  # nothing is queued: the frame only gets its number
        own.add_place(kw if keypoints else words, frame, kps)


def bench(model: str, places: int, keypoints: int) -> dict:
    det = load_detector(model, DetectorConfig())
    fill_map(det, places, keypoints)
    clocks = (time.perf_counter, time.process_time)  # wall and CPU: the machine may be shared
    with tempfile.TemporaryDirectory(prefix="state_bench_") as tmp:
        with MapStateDir(tmp, bundle_id(det.manifest)) as d:
            t0 = [c() for c in clocks]
            state = det.state()
            t1 = [c() for c in clocks]
            info = d.save(state)
            t2 = [c() for c in clocks]
        del state
        again = load_detector(model, DetectorConfig())
        with MapStateDir(tmp, bundle_id(again.manifest)) as d:
            t3 = [c() for c in clocks]
            load_into(again, d)
            t4 = [c() for c in clocks]
    assert again.n_places == det.n_places and again.map_bytes() == det.map_bytes()
    return {
        "places": places, "keypoints_per_place": keypoints, "vocabulary": det.map.vocabulary_size,
        "state_s": round(t1[0] - t0[0], 3), "save_s": round(t2[0] - t1[0], 3), "load_s": round(t4[0] - t3[0], 3),
        "state_cpu_s": round(t1[1] - t0[1], 3), "save_cpu_s": round(t2[1] - t1[1], 3),
        "load_cpu_s": round(t4[1] - t3[1], 3), "load_average": os.getloadavg()[0],
        "bytes": info.nbytes, "bytes_per_place": round(info.nbytes / places), "map_bytes": det.map_bytes(),
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", required=True, metavar="BUNDLE")
    p.add_argument("--places", type=int, nargs="+", default=[1000, 10000])
    p.add_argument("--keypoints", type=int, default=500, help="stored keypoints per place (default 500)")
    args = p.parse_args(argv)
    for n in args.places:
        print(json.dumps(bench(args.model, n, args.keypoints)), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
