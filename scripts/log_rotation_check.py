"""Measure a rotated, budgeted node log end to end (docs/streaming.md, "Log files").

Runs `aefabmap run --mcap OUT/logs/ --mcap-max-mb MAX --log-budget-mb BUDGET` as a child
process, publishes FRAMES synthetic 640x480 JPEG frames (60 distinct views of the synthetic
route, looped) over loopback Zenoh, samples the bytes of the log set on disk while it runs,
stops the node, reads every remaining file with the `mcap` package's own reader, then runs
`aefabmap replay OUT/logs --check`. Prints and writes OUT/log_rotation.json.

    PYTHONPATH=. python scripts/log_rotation_check.py --out /tmp/logrot [--frames 3000] [--rate 25]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import threading
import time
from pathlib import Path

from mcap.reader import make_reader

from aefabmap.cli.demo import default_bundle
from aefabmap_runtime.adapters.log_set import LogSet
from aefabmap_runtime.adapters.zenoh_transport import SessionConfig, stats_key_for, result_key_for
from aefabmap_runtime.core.records.messages import StatsMessage
from aefabmap_runtime.tools.node_process import connect_when_listening, free_tcp_port, stop_node
from aefabmap_runtime.tools.publisher import images_dir_source, publish_frames
from aefabmap_runtime.tools.synthetic_route import make_demo_sequence

KEY = "logrot/camera/image"
MB = 1024 * 1024


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--frames", type=int, default=3000)
    p.add_argument("--rate", type=float, default=25.0)
    p.add_argument("--max-mb", type=float, default=5.0)
    p.add_argument("--budget-mb", type=float, default=20.0)
    args = p.parse_args()
    out: Path = args.out
    seq, logs = out / "sequence", out / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    if len(list(seq.glob("frame_*.jpg"))) != 60:
        make_demo_sequence(seq, n_frames=60, seed=0)
    model = default_bundle()
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    cmd = [sys.executable, "-m", "aefabmap.cli.main", "run", "--model", str(model), "--key", KEY,
           "--listen", endpoint, "--mcap", f"{logs}/", "--mcap-max-mb", str(args.max_mb),
           "--log-budget-mb", str(args.budget_mb), "--queue", str(args.frames), "--max-places", "500"]
    print(" ".join(cmd[2:]), flush=True)
    node = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    log_set = LogSet(f"{logs}/")
    peak = {"bytes": 0, "files": 0}
    done, last_stats = threading.Event(), {}

    def sample_disk() -> None:
        while not done.wait(0.1):
            files = log_set.files()
            peak["bytes"] = max(peak["bytes"], sum(f.size for f in files))
            peak["files"] = max(peak["files"], len(files))

    sampler = threading.Thread(target=sample_disk, daemon=True)
    sampler.start()
    t0 = time.monotonic()
    session = connect_when_listening(endpoint, node, 60)
    finished = threading.Event()

    def on_stats(sample) -> None:
        msg = StatsMessage.from_json(sample.payload.to_bytes())
        last_stats["msg"] = msg
        if msg.frames_processed + msg.dropped >= args.frames:
            finished.set()

    sub = session.declare_subscriber(stats_key_for(result_key_for(KEY)), on_stats)
    pub = publish_frames(SessionConfig(connect=(endpoint,)), KEY, images_dir_source(seq), rate_hz=args.rate,
                         count=args.frames, loop=True, wait_for_subscriber_s=60)
    finished.wait(600)
    sub.undeclare()
    session.close()
    summary = stop_node(node)
    done.set()
    sampler.join()
    wall = time.monotonic() - t0
    left = log_set.files()
    files = []
    for f in left:
        with open(f.path, "rb") as fh:
            reader = make_reader(fh)
            s = reader.get_summary()
            counts = {}
            for _, ch, _ in reader.iter_messages():
                counts[ch.topic] = counts.get(ch.topic, 0) + 1
            files.append({"name": f.path.name, "bytes": f.size, "summary": s is not None,
                          "metadata": sorted(m.name for m in reader.iter_metadata()), "messages": counts})
    replay_cmd = [sys.executable, "-m", "aefabmap.cli.main", "replay", str(logs), "--model", str(model), "--check"]
    t1 = time.monotonic()
    rep = subprocess.run(replay_cmd, capture_output=True, text=True, timeout=1800, check=False)
    replay_doc = json.loads(rep.stdout.strip().splitlines()[-1]) if rep.stdout.strip() else {}
    report = {
        "frames_published": pub.published, "publish_rate_hz": args.rate, "wall_s": round(wall, 1),
        "max_mb": args.max_mb, "budget_mb": args.budget_mb,
        "run_summary": summary.to_dict() if summary else None,
        "last_stats": {k: getattr(last_stats.get("msg"), k, None) for k in ("frames_processed", "dropped",
                                                                          "log_errors", "log_state")},
        "files_written": len(summary.log_files) if summary else None,
        "files_deleted": summary.log_files_deleted if summary else None,
        "files_left": len(left), "bytes_left": sum(f.size for f in left),
        "largest_file_bytes": max((f.size for f in left), default=0),
        "peak_bytes_on_disk": peak["bytes"], "peak_files_on_disk": peak["files"],
        "budget_bytes": int(args.budget_mb * MB),
        "all_closed_files_read_by_mcap_reader": all(f["summary"] for f in files),
        "files": files,
        "replay": {"exit_code": rep.returncode, "seconds": round(time.monotonic() - t1, 1),
                   "frames_read": replay_doc.get("frames_read"), "frames_processed": replay_doc.get("frames_processed"),
                   "files": len((replay_doc.get("status") or {}).get("files") or []),
                   "check": {k: (replay_doc.get("check") or {}).get(k)
                             for k in ("ok", "compared", "matched", "mismatched", "notes")}},
    }
    text = json.dumps(report, indent=1)
    (out / "log_rotation.json").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
