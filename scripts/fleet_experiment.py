"""Two (or three) robots of a fleet on loopback through a Zenoh router, with real `aefabmap run`
processes: robot a streams the first frames of a sequence, robot b (started after a finished,
its own map empty) streams the rest; b's loops to a's places are scored against the ground truth.

    python scripts/fleet_experiment.py --model BUNDLE --images DATA/lip6_outdoor \
        --gt DATA/lip6_outdoor/ground_truth.npy --split 600 --out fleet.json [--baseline] \
        [--kill-a-after 200] [--late-joiner] [--tls]

Frames go one at a time, the next once the node's result arrived (closed loop: no frame is
dropped, and frames/s is what the node sustains). --baseline runs b once more without the fleet
(frames/s, latency); --kill-a-after N kills robot a (SIGKILL) after b's N-th frame;
--late-joiner starts a third robot c after b and reports what it holds. --a-offline: robot a
runs without the fleet; its log is then offered by `aefabmap replay LOG --fleet` (a map built
offline), which b's loops go to. --tls: the router and the robots run the shipped fleet configs
with mutual TLS and access control (deploy/zenoh-fleet-router.json5, zenoh-fleet-robot.json5),
with certificates made for the run (scripts/fleet_tls.py; needs the openssl command).
"""

from __future__ import annotations

import argparse
import json
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from aefabmap_runtime.adapters.frames import ENCODING_JPEG, ENCODING_PNG
from aefabmap_runtime.adapters.image_folder import list_images
from aefabmap_runtime.adapters.zenoh_transport import (
    FramePublisher,
    SessionConfig,
    open_session,
    result_key_for,
    stats_key_for,
)
from aefabmap_runtime.core.records.messages import FrameResult, StatsMessage
from aefabmap_runtime.tools.node_process import (
    connect_when_listening,
    free_tcp_port,
    process_rss_mb,
    start_run_node,
    stop_node,
)
from aefabmap_runtime.tools.pr_metrics import correct_predictions

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fleet_tls import make_certificates, robot_config, router_config  # noqa: E402


class Router:
    """The fleet's Zenoh router on loopback, plain or with the shipped TLS + access-control config;
    `join(name, listen)`: the arguments that make a robot's node (listening on `listen`) join it."""

    def __init__(self, args, work: Path) -> None:
        self.args, self.port = args, free_tcp_port()
        self.tls = work / "tls" if args.tls else None
        if self.tls is not None:
            self.tls.mkdir()
            make_certificates(self.tls, ("fleet-router", "a", "b", "c"))
            self.session = open_session(SessionConfig(config_file=str(router_config(self.tls, self.port))))
        else:
            self.session = open_session(SessionConfig(listen=(self.endpoint,), mode="router"))

    @property
    def endpoint(self) -> str:
        return f"tcp/127.0.0.1:{self.port}"

    def join(self, name: str, listen: str) -> list[str]:
        if self.tls is None:
            where = ["--connect", self.endpoint]
        else:
            where = ["--config", str(robot_config(self.tls, name, self.port, listen))]
        return [*where, "--fleet", self.args.fleet, "--robot", name]

    def close(self) -> None:
        self.session.close()


class Robot:
    """One `aefabmap run` child with its key, its results and its last stats."""

    def __init__(self, name: str, args, router: Router | None, work: Path, extra_args: tuple[str, ...] = ()) -> None:
        self.name, self.key = name, f"fleet_{name}/camera/image"
        self.endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
        extra = ["--exclude", str(args.exclude), *extra_args]
        if router is not None:
            extra += router.join(name, self.endpoint)
        self.proc = start_run_node(args.model, self.key, self.endpoint, work / f"{name}.mcap",
                                   work / f"{name}.log", extra)
        self.session = connect_when_listening(self.endpoint, self.proc, 60)
        self.results: list[FrameResult] = []
        self.stats: StatsMessage | None = None
        self.cond = threading.Condition()
        rkey = result_key_for(self.key)
        self.subs = [self.session.declare_subscriber(rkey, self._on_result),
                     self.session.declare_subscriber(stats_key_for(rkey), self._on_stats)]
        self.pub = FramePublisher(self.session, self.key, congestion="block")
        if not self.pub.wait_for_subscriber(60):
            raise SystemExit(f"robot {name}: the node did not subscribe")

    def _on_result(self, sample) -> None:
        r = FrameResult.from_json(sample.payload.to_bytes())
        with self.cond:
            self.results.append(r)
            self.cond.notify_all()

    def _on_stats(self, sample) -> None:
        self.stats = StatsMessage.from_json(sample.payload.to_bytes())

    def stream(self, paths: list[Path], on_frame=None) -> float:
        """Send each image, waiting for its result; returns the seconds it took."""
        t0 = time.monotonic()
        for i, p in enumerate(paths):
            data = p.read_bytes()
            enc = ENCODING_JPEG if p.suffix.lower() in (".jpg", ".jpeg") else ENCODING_PNG
            with self.cond:
                n = len(self.results)
            self.pub.put(data, enc, stamp_ns=time.time_ns())
            with self.cond:
                if not self.cond.wait_for(lambda: len(self.results) > n, 60):
                    raise SystemExit(f"robot {self.name}: no result for frame {i}")
            if on_frame is not None:
                on_frame(i)
        return time.monotonic() - t0

    def stop(self) -> dict:
        rss = process_rss_mb(self.proc.pid)
        summary = stop_node(self.proc, 60)
        self.release()
        return {"summary": summary.to_dict() if summary else None, "rss_mb_at_end": rss}

    def release(self) -> None:
        """Close this side's session to the node (also after the node was killed: an open
        session to a dead peer keeps the interpreter from exiting)."""
        for s in self.subs:
            s.undeclare()
        self.pub.close()
        self.session.close()


class OfferedLog:
    """A `replay LOG --fleet` child that offers the map of a log; `offered`: its report line."""

    def __init__(self, proc: subprocess.Popen, offered: dict) -> None:
        self.proc, self.offered = proc, offered


def offer_log(args, log: Path, router: Router, stderr_path: Path) -> OfferedLog:
    """Replay `log` as robot a of the fleet and wait until it offers its map (the "offering" line)."""
    listen = f"tcp/127.0.0.1:{free_tcp_port()}"
    cmd = [sys.executable, "-m", "aefabmap.cli.main", "replay", str(log), "--model", args.model,
           "--listen", listen, *router.join("a", listen)]
    t0 = time.monotonic()
    with open(stderr_path, "w") as err:
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=err, text=True)
    while time.monotonic() - t0 < 600:
        line = next((x for x in stderr_path.read_text().splitlines() if "offering" in x), None)
        if line is not None:
            return OfferedLog(proc, {"line": line.split(": ", 1)[-1], "seconds": round(time.monotonic() - t0, 2)})
        if proc.poll() is not None:
            raise SystemExit(f"replay --fleet exited ({proc.returncode}): {stderr_path}")
        time.sleep(0.2)
    raise SystemExit("replay --fleet did not finish its replay in time")


def score(results: list[FrameResult], gt: np.ndarray, offset: int, remote_offset: int, tolerance: int) -> dict:
    """Right / wrong loops of robot b: to a's places (frame numbers from remote_offset) and to its own."""
    out = {}
    for kind in ("remote", "own"):
        rows = [r for r in results if r.verified and ((r.verified_robot is not None) == (kind == "remote"))]
        first = remote_offset if kind == "remote" else offset
        pred = np.full(gt.shape[0], -1)
        for r in rows:
            pred[offset + r.sequence] = first + r.verified_frame
        ok = correct_predictions(pred, gt, tolerance)
        right = int(sum(ok[offset + r.sequence] for r in rows))
        out[kind] = {"loops": len(rows), "right": right, "wrong": len(rows) - right}
    return out


def latency(results: list[FrameResult]) -> dict:
    lat = np.array([r.latency_ms for r in results if r.latency_ms is not None])
    return {"p50_ms": round(float(np.median(lat)), 2), "p95_ms": round(float(np.percentile(lat, 95)), 2)} if lat.size else {}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", required=True)
    ap.add_argument("--images", required=True, type=Path)
    ap.add_argument("--gt", required=True, type=Path)
    ap.add_argument("--split", type=int, default=600, help="robot a streams frames [0, split), b the rest")
    ap.add_argument("--exclude", type=int, default=50)
    ap.add_argument("--tolerance", type=int, default=10)
    ap.add_argument("--fleet", default="lip6")
    ap.add_argument("--baseline", action="store_true", help="run b again without the fleet")
    ap.add_argument("--kill-a-after", type=int, default=None, metavar="N")
    ap.add_argument("--late-joiner", action="store_true")
    ap.add_argument("--a-offline", action="store_true", help="a's places come from `replay --fleet` of its log")
    ap.add_argument("--tls", action="store_true", help="the shipped fleet configs: mutual TLS, access control")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    paths = list_images(args.images)
    gt = np.load(args.gt)
    work = Path(tempfile.mkdtemp(prefix="aefabmap-fleet-"))
    router = Router(args, work)
    doc: dict = {"model": args.model, "images": str(args.images), "split": args.split, "work": str(work),
                 "tls": args.tls}
    a = Robot("a", args, None if args.a_offline else router, work)
    doc["a_seconds"] = round(a.stream(paths[: args.split]), 2)
    time.sleep(6)  # one stats period: a's counters after its last frame
    offline = None
    if args.a_offline:
        doc["a"] = {"stats": a.stats.to_dict() if a.stats else None, **a.stop()}
        offline = offer_log(args, work / "a.mcap", router, work / "a_replay.log")
        doc["a_offline"] = offline.offered
    b = Robot("b", args, router, work)

    def maybe_kill(i: int) -> None:
        if args.kill_a_after is not None and i + 1 == args.kill_a_after and a.proc.poll() is None:
            a.proc.send_signal(signal.SIGKILL)
            doc["a_killed_after_b_frame"] = i + 1

    seconds = b.stream(paths[args.split:], maybe_kill)
    time.sleep(6)
    rest = paths[args.split:]
    doc["b"] = {"frames": len(rest), "seconds": round(seconds, 2), "fps": round(len(rest) / seconds, 2),
                "latency": latency(b.results), **score(b.results, gt, args.split, 0, args.tolerance),
                "stats": b.stats.to_dict() if b.stats else None}
    if offline is None:
        doc["a"] = {"stats": a.stats.to_dict() if a.stats else None}
    if args.late_joiner:
        c = Robot("c", args, router, work)
        c.stream(paths[:1])
        time.sleep(6)
        doc["c"] = {"stats": c.stats.to_dict() if c.stats else None, **c.stop()}
    doc["b"].update(b.stop())
    if a.proc.poll() is None:
        doc["a"].update(a.stop())
    elif offline is None:
        a.release()
    if offline is not None:
        offline.proc.send_signal(signal.SIGTERM)
        doc["a_offline"]["exit_code"] = offline.proc.wait(60)
    if args.baseline:
        b0 = Robot("b0", args, None, work)
        s0 = b0.stream(rest)
        doc["b_without_fleet"] = {"seconds": round(s0, 2), "fps": round(len(rest) / s0, 2),
                                  "latency": latency(b0.results), "own_loops": sum(r.verified for r in b0.results),
                                  **b0.stop()}
    router.close()
    args.out.write_text(json.dumps(doc, indent=2) + "\n")
    print(json.dumps({k: v for k, v in doc.items() if k != "a"}, indent=2)[:6000])
    return 0


if __name__ == "__main__":
    sys.exit(main())
