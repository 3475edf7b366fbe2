"""Localization against a map built once, with real `aefabmap run` processes on loopback
(docs/localization.md): a map is built by `run --state M` over the first frames of a sequence,
then `run --state M --localize` streams the rest; its verified loops are scored against the
ground truth, the state directory is hashed before and after, and the node's RSS is read at
start, every 50 frames and at the end; 20 of those frames are then sent to the running node's
"where am I?" queryable and its answers scored. Then a localize run is killed (SIGKILL) mid-way
and M hashed again, and `eval --localize` scores the same frames in one process.

    python scripts/localize_experiment.py --model BUNDLE --images DATA/lip6_outdoor \\
        --gt DATA/lip6_outdoor/ground_truth.npy --split 600 --out localize.json

Frames go one at a time, the next once the node's result arrived (closed loop, as
scripts/fleet_experiment.py, whose robot client it uses).
"""

from __future__ import annotations

import argparse
import json
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fleet_experiment import Robot  # noqa: E402

from aefabmap_runtime.adapters.image_folder import list_images  # noqa: E402
from aefabmap_runtime.tools.localize_eval import state_digest  # noqa: E402
from aefabmap_runtime.tools.node_process import process_rss_mb  # noqa: E402
from aefabmap_runtime.tools.pr_metrics import correct_predictions  # noqa: E402


def scored(results, gt: np.ndarray, tolerance: int) -> dict:
    """Verified loops of the localize run, right / wrong by the ground truth (tolerant)."""
    pred = np.full(gt.shape[0], -1)
    for r in results:
        if r.verified:
            pred[r.sequence] = r.verified_frame
    ok = correct_predictions(pred, gt, tolerance)
    loops = [r for r in results if r.verified]
    right = int(sum(ok[r.sequence] for r in loops))
    return {"frames": len(results), "loops": len(loops), "right": right, "wrong": len(loops) - right}


def locate_queries(robot: Robot, paths: list[Path], gt: np.ndarray, args) -> dict:
    """Send 20 frames of the second part, evenly spaced from its frame `--exclude` on (the map holds
    its run's last frames, which the ground truth does not pair with the frames just after them),
    to the running node's locate queryable
    (at its rate: a "busy" answer is asked again after a pause); each answer right or wrong by
    the ground truth (tolerant)."""
    import threading

    from aefabmap_runtime.adapters.zenoh_transport import locate_key_for, result_key_for
    from aefabmap_runtime.core.records.messages import LocateAnswer

    key, pause = locate_key_for(result_key_for(robot.key)), threading.Event()
    picks = np.linspace(args.split + args.exclude, len(paths) - 1, 20).round().astype(int)
    rows = []
    for i in picks:
        data = paths[i].read_bytes()
        for _ in range(50):
            reply = next(iter(robot.session.get(key, payload=data, timeout=30)), None)
            if reply is not None and reply.ok is None and reply.err.payload.to_string().startswith("busy"):
                pause.wait(0.25)
                continue
            break
        answer = LocateAnswer.from_json(reply.ok.payload.to_bytes()) if reply is not None and reply.ok else None
        pred = np.full(gt.shape[0], -1)
        if answer is not None and answer.verified:
            pred[i] = answer.frame
        right = bool(correct_predictions(pred, gt, args.tolerance)[i]) if pred[i] >= 0 else None
        rows.append({"frame": int(i), "verified": bool(answer and answer.verified),
                     "place_frame": answer.frame if answer else None, "right": right,
                     "latency_ms": answer.latency_ms if answer else None})
    verified = [r for r in rows if r["verified"]]
    return {"queries": len(rows), "verified": len(verified), "right": sum(bool(r["right"]) for r in verified),
            "wrong": sum(r["right"] is False for r in verified), "answers": rows}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", required=True)
    ap.add_argument("--images", required=True, type=Path)
    ap.add_argument("--gt", required=True, type=Path)
    ap.add_argument("--split", type=int, default=600, help="the map is built over frames [0, split)")
    ap.add_argument("--exclude", type=int, default=50)
    ap.add_argument("--tolerance", type=int, default=10)
    ap.add_argument("--kill-after", type=int, default=100, help="frames the killed localize run gets")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    paths = list_images(args.images)
    gt = np.load(args.gt)
    work = Path(tempfile.mkdtemp(prefix="aefabmap-localize-"))
    state = work / "map"
    doc: dict = {"model": args.model, "images": str(args.images), "split": args.split, "work": str(work)}

    mapper = Robot("mapper", args, None, work, ("--state", str(state)))
    doc["map_seconds"] = round(mapper.stream(paths[: args.split]), 2)
    doc["map"] = mapper.stop()
    doc["state_sha256_before"] = state_digest(state)

    loc = Robot("localizer", args, None, work, ("--state", str(state), "--localize"))
    rss: dict[int, float | None] = {}  # frames streamed -> the node's RSS (MB)

    def sample_rss(i: int) -> None:
        if i % 50 == 0 or i == len(paths) - args.split - 1:
            rss[i + 1] = process_rss_mb(loc.proc.pid)

    seconds = loc.stream(paths[args.split:], sample_rss)
    doc["locate"] = locate_queries(loc, paths, gt, args)
    doc["localize"] = {"seconds": round(seconds, 2), **scored(loc.results, gt, args.tolerance),
                       "rss_mb_by_frames": rss,
                       "places": loc.results[-1].n_places if loc.results else None, **loc.stop()}
    doc["state_sha256_after_localize"] = state_digest(state)

    killed = Robot("killed", args, None, work, ("--state", str(state), "--localize"))
    killed.stream(paths[args.split: args.split + args.kill_after])
    killed.proc.send_signal(signal.SIGKILL)
    killed.proc.wait(30)
    killed.release()
    doc["state_sha256_after_kill"] = state_digest(state)

    t0 = time.monotonic()
    ev = subprocess.run([sys.executable, "-m", "aefabmap.cli.main", "eval", "--model", args.model, "--images",
                         str(args.images), "--gt", str(args.gt), "--state", str(state), "--localize", "--exclude",
                         str(args.exclude), "--tolerance", str(args.tolerance), "--no-progress", "--json",
                         str(work / "eval_localize.json")], capture_output=True, text=True, check=False)
    doc["eval_localize"] = {"exit_code": ev.returncode, "seconds": round(time.monotonic() - t0, 2),
                            "metrics": json.loads((work / "eval_localize.json").read_text())
                            if ev.returncode == 0 else ev.stderr[-2000:]}
    doc["state_sha256_after_eval"] = state_digest(state)
    doc["state_unchanged"] = len({doc[k] for k in doc if k.startswith("state_sha256")}) == 1
    args.out.write_text(json.dumps(doc, indent=2) + "\n")
    print(json.dumps({k: v for k, v in doc.items() if k not in ("map",)}, indent=2)[:6000])
    return 0


if __name__ == "__main__":
    sys.exit(main())
