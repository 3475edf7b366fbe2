"""`aefabmap demo`: the main job end to end on loopback, with nothing but the project.

Two processes over Zenoh: this one publishes camera frames and listens to results; a child
`aefabmap run` process detects loop closures and writes the MCAP log. Then the log is
replayed offline with `--check` semantics. Default data: the synthetic loop sequence and the
bundle shipped in the package (trained on other synthetic worlds, see aefabmap/data/README.md).
"""

from __future__ import annotations

import json
import logging
import queue
import subprocess
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from aefabmap.cli.options import default_bundle
from aefabmap_runtime.errors import AefabmapError, DataNotFoundError, TransportError

if TYPE_CHECKING:
    from aefabmap_runtime.core.records.messages import FrameResult

log = logging.getLogger("aefabmap.demo")
DEMO_KEY = "aefabmap/demo/camera/image"


def register(sub) -> None:
    p = sub.add_parser("demo", help="end-to-end demo on loopback: publish -> run -> loop closures -> MCAP -> replay check")
    data = p.add_argument_group("model and frames")
    data.add_argument("--model", type=Path, default=None, metavar="BUNDLE", help="model bundle (default: the shipped one)")
    data.add_argument("--images", type=Path, default=None, metavar="DIR", help="stream these images instead of the synthetic sequence")
    data.add_argument("--gt", type=Path, default=None, metavar="GT.npy", help="ground truth of --images, to score the loops")
    data.add_argument("--frames", type=int, default=240, help="synthetic frames (default 240: two laps of one route)")
    live = p.add_argument_group("streaming")
    live.add_argument("--rate", type=float, default=8.0, help="publish rate in Hz (default 8)")
    live.add_argument("--timeout", type=float, default=60.0,
                      help="seconds to wait for the runtime at start and for results (default 60)")
    out = p.add_argument_group("output")
    out.add_argument("--out", type=Path, default=Path("aefabmap-demo"),
                     help="output directory: frames, MCAP log (default ./aefabmap-demo)")
    p.set_defaults(func=run)


def run(args) -> int:
    from aefabmap_runtime.adapters.zenoh_transport import SessionConfig, result_key_for
    from aefabmap_runtime.core.records.messages import FrameResult
    from aefabmap_runtime.tools.node_process import (
        connect_when_listening,
        free_tcp_port,
        stop_node,
    )
    from aefabmap_runtime.tools.publisher import images_dir_source, publish_frames

    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    model = args.model or default_bundle()
    images_dir, gt_path = _prepare_images(args, out)
    n_frames = len([p for p in images_dir.iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png")])
    mcap_path = out / "demo.mcap"
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    cmd = [sys.executable, "-m", "aefabmap.cli.main", "run", "--model", str(model), "--key", DEMO_KEY,
           "--listen", endpoint, "--mcap", str(mcap_path), "--queue", "4"]
    print(f"runtime:   {' '.join(cmd[2:])}", flush=True)
    node = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=None, text=True)
    results: queue.Queue = queue.Queue()
    session = None

    def on_result(sample) -> None:
        try:
            results.put(FrameResult.from_json(sample.payload.to_bytes()))
        except AefabmapError as exc:  # a malformed message: say so, keep listening
            log.warning("ignored a result message: %s", exc)

    try:
        session = connect_when_listening(endpoint, node, args.timeout)
        sub = session.declare_subscriber(result_key_for(DEMO_KEY), on_result)
        print(f"publisher: {n_frames} frames from {images_dir} at {args.rate} Hz on {DEMO_KEY} via {endpoint}", flush=True)
        pub = publish_frames(SessionConfig(connect=(endpoint,)), DEMO_KEY, images_dir_source(images_dir),
                             rate_hz=args.rate, wait_for_subscriber_s=args.timeout)
        if not pub.matched:
            raise TransportError(f"the runtime did not subscribe to {DEMO_KEY} within {args.timeout} s")
        _collect(results, pub.published, first_timeout=args.timeout, idle_timeout=10.0)
        sub.undeclare()
    finally:
        if session is not None:
            session.close()
        summary = stop_node(node)
    print(f"runtime summary: {json.dumps(summary.to_dict())}" if summary else "runtime gave no summary")
    if summary is not None:  # the log actually written: demo-0001.mcap... when demo.mcap exists (never overwritten)
        mcap_path = Path(summary.mcap_path)
    _report(_logged_results(mcap_path), gt_path, n_frames)
    return _replay_check(model, mcap_path)


def _prepare_images(args, out: Path) -> tuple[Path, Path | None]:
    if args.images is not None:
        if not args.images.is_dir():
            raise DataNotFoundError(f"image directory {args.images} does not exist")
        return args.images, args.gt
    from aefabmap_runtime.tools.synthetic_route import make_demo_sequence

    seq = out / "sequence"
    if not (seq / "gt.npy").is_file() or len(list(seq.glob("frame_*.jpg"))) != args.frames:
        print(f"generating {args.frames} synthetic frames in {seq} ...", flush=True)
        make_demo_sequence(seq, n_frames=args.frames, seed=0)
    return seq, seq / "gt.npy"


def _collect(results: queue.Queue, expected: int, first_timeout: float, idle_timeout: float) -> list[FrameResult]:
    """Print results as they arrive, until `expected` came or none came for idle_timeout s."""
    got = []
    while len(got) < expected:
        try:
            r = results.get(timeout=idle_timeout if got else first_timeout)
        except queue.Empty:
            break
        got.append(r)
        if r.loop:
            how = f"{r.inliers} inliers ({r.geometry_model})" if r.verified else f"score {r.score:.4f}"
            print(f"  LOOP  frame {r.sequence:4d} -> frame {_match_frame(r):4d}, {how}", flush=True)
    return got


def _match_frame(result: FrameResult) -> int:
    """The earlier frame a loop closure points at: the verified one when verification ran."""
    return result.verified_frame if result.verified else result.best_frame


def _logged_results(mcap_path: Path) -> list[FrameResult]:
    """Results as the runtime logged them (complete even if live messages were missed)."""
    from aefabmap_runtime.adapters.mcap_log import McapLogReader

    reader = McapLogReader(mcap_path)
    for _ in reader.frames():
        pass  # one pass reads images, results, stats and metadata
    return reader.results


def _report(received: list[FrameResult], gt_path: Path | None, n_frames: int) -> None:
    loops = [r for r in received if r.loop]
    print(f"frames processed: {len(received)}, loop closures: {len(loops)}")
    if gt_path is None or not gt_path.is_file() or not received:
        return
    from aefabmap_runtime.tools.sequence_eval import load_ground_truth

    gt = load_ground_truth(gt_path, n_frames)  # InputError when it does not fit the frames
    ok = sum(bool(gt[r.sequence, max(0, _match_frame(r) - 10): _match_frame(r) + 11].any()) for r in loops)
    revisits = int(np.tril(gt, -1).any(axis=1).sum())
    print(f"against ground truth: {ok}/{len(loops)} loop closures correct (10-frame tolerance); "
          f"{revisits} frames revisit a place")


def _replay_check(model: Path, mcap_path: Path) -> int:
    from aefabmap_runtime.adapters.bundle_reader import load_detector
    from aefabmap_runtime.adapters.replay import replay

    try:
        summary = replay(load_detector(model), mcap_path, check=True)
    except AefabmapError as exc:
        print(f"replay failed: {exc}")
        return exc.exit_code
    report = summary.check
    print(f"MCAP log: {mcap_path} (open it in Foxglove)")
    print(f"replay --check: {report.describe()}")
    return 0 if report.ok else 1
