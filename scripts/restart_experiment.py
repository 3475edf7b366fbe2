#!/usr/bin/env python
"""The map survives a restart: an image sequence through `aefabmap run --state` processes, stopped
after frame SPLIT-1 (SIGTERM, or kill -9 with --kill), restarted with the same state for the rest,
compared with an uninterrupted in-process run of the same bundle (the same detector the node runs).

Prints JSON lines: the first run (exit code, state's frame counter, frames lost, state bytes), then
(SIGTERM mode) whether every result field but timings/transport/stamps is identical, loops after
the restart vs uninterrupted, and how many of them match frames stored before the restart and
hit the ground truth exactly (gt[i, j], no tolerance). Usage:

    python scripts/restart_experiment.py --model BUNDLE --images DIR --gt GT.npy --split 600 --work OUT_DIR [--kill]
"""

from __future__ import annotations

import argparse
import json
import queue
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from aefabmap_runtime.adapters.bundle_reader import load_detector
from aefabmap_runtime.adapters.frame_loop import FrameLoop
from aefabmap_runtime.adapters.image_folder import list_images
from aefabmap_runtime.adapters.state_dir import MapStateDir, bundle_id, load_into
from aefabmap_runtime.adapters.mcap_log import McapLogReader
from aefabmap_runtime.adapters.replay import NONDETERMINISTIC_FIELDS
from aefabmap_runtime.adapters.zenoh_transport import (
    FramePublisher,
    SessionConfig,
    open_session,
)
from aefabmap_runtime.core.detector import DetectorConfig
from aefabmap_runtime.core.run_config import MAX_QUEUE

CLI = [sys.executable, "-m", "aefabmap.cli.main"]
KEY = "restart/camera/image"
IGNORED = (*NONDETERMINISTIC_FIELDS, "stamp_ns")


def _fields(doc: dict) -> dict:
    return {k: v for k, v in doc.items() if k not in IGNORED}


def run_part(args, images_dir: Path, mcap: Path, last_seq: int, port: int, stop: int) -> tuple[int, str, float]:
    """One `run` process fed images_dir; stopped with ``stop`` once result ``last_seq`` is out."""
    ep = f"tcp/127.0.0.1:{port}"
    run = subprocess.Popen(CLI + ["run", "--model", str(args.model), "--key", KEY, "--listen", ep, "--mcap", str(mcap),
                                  "--queue", str(MAX_QUEUE), "--state", str(args.work / "state"),
                                  "--snapshot-every", args.snapshot_every],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    docs: queue.Queue = queue.Queue()
    try:
        with open_session(SessionConfig(connect=(ep,))) as s:
            sub = s.declare_subscriber(KEY.rsplit("/", 1)[0] + "/lcd",
                                       lambda smp: docs.put(json.loads(smp.payload.to_bytes())))
            probe = FramePublisher(s, KEY)
            if not probe.wait_for_subscriber(120):
                run.kill()
                raise SystemExit(f"the node never subscribed: {run.communicate(timeout=30)[1].strip()[-500:]}")
            probe.close()
            t0 = time.monotonic()
            subprocess.run(CLI + ["publish", "--images", str(images_dir), "--key", KEY, "--rate", str(args.rate),
                                  "--connect", ep], check=True, capture_output=True, timeout=3600)
            while docs.get(timeout=600)["sequence"] != last_seq:
                pass
            elapsed = time.monotonic() - t0
            sub.undeclare()
        run.send_signal(stop)
        _, err = run.communicate(timeout=300)
    finally:
        if run.poll() is None:
            run.kill()
            run.wait(10)
    return run.returncode, err, elapsed


def logged_results(path: Path) -> list[dict]:
    reader = McapLogReader(path)
    for _ in reader.frames():  # results are collected while reading
        pass
    return [_fields(r.to_dict()) for r in reader.results]


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", required=True, type=Path)
    p.add_argument("--images", required=True, type=Path)
    p.add_argument("--gt", type=Path, default=None)
    p.add_argument("--split", type=int, required=True, help="first frame of the second run")
    p.add_argument("--work", required=True, type=Path, help="new directory for links, logs and the state")
    p.add_argument("--snapshot-every", default="100p")
    p.add_argument("--rate", type=float, default=40.0)
    p.add_argument("--kill", action="store_true", help="stop the first run with kill -9 instead of SIGTERM")
    args = p.parse_args()
    frames = list_images(args.images)
    args.work.mkdir(parents=True)
    for name, part in (("first", frames[: args.split]), ("second", frames[args.split:])):
        (args.work / name).mkdir()
        for f in part:
            (args.work / name / f.name).symlink_to(f.resolve())
    rc, _, t = run_part(args, args.work / "first", args.work / "first.mcap", args.split - 1, 17601,
                        signal.SIGKILL if args.kill else signal.SIGTERM)
    det = load_detector(args.model, DetectorConfig())
    with MapStateDir(args.work / "state", bundle_id(det.manifest)) as d:
        state = d.load()  # None: killed before the first snapshot
        snap = d.path / d.current() if state is not None else None
        load_into(det, d)  # the snapshot, then the journal of the frames after it
    snapshot_seq = int(state.scalars["sequence"]) if state is not None else 0
    saved = det.next_sequence
    print(json.dumps({"stop": "kill -9" if args.kill else "SIGTERM", "exit_code": rc, "seconds": round(t, 1),
                      "snapshot_sequence": snapshot_seq, "state_sequence": saved, "frames_lost": args.split - saved,
                      "state_bytes": sum(f.stat().st_size for f in snap.iterdir()) if snap else 0}), flush=True)
    if args.kill:
        return 0
    rc2, _, t2 = run_part(args, args.work / "second", args.work / "second.mcap", len(frames) - 1, 17602, signal.SIGTERM)
    got = logged_results(args.work / "first.mcap") + logged_results(args.work / "second.mcap")
    loop = FrameLoop(load_detector(args.model, DetectorConfig()))
    ref = [_fields(loop.step_file(f, i).result.to_dict()) for i, f in enumerate(frames)]

    def loops(rs):
        return [(r["sequence"], r["verified_frame"]) for r in rs if r["loop"] and r["sequence"] >= args.split]

    after, after_ref = loops(got), loops(ref)
    out = {"exit_code": rc2, "seconds": round(t2, 1), "frames": len(got), "identical_results": got == ref,
           "frames_differing": sum(a != b for a, b in zip(got, ref)) + abs(len(got) - len(ref)),
           "loops_after_restart": len(after), "loops_after_uninterrupted": len(after_ref),
           "same_loops": after == after_ref, "to_frames_before_restart": sum(j < args.split for _, j in after)}
    if args.gt is not None:
        gt = np.load(args.gt, allow_pickle=False)
        out["exact_gt_hits"] = int(sum(bool(gt[i, j]) for i, j in after))
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
