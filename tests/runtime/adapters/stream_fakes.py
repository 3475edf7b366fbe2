"""Helpers of the streaming-runtime tests: free ports, a stand-in detector, waiting utilities.

The stand-in detector only mimics the interface of aefabmap_runtime.core.detector.LoopClosureDetector
(process(gray, stamp_ns) -> result with to_dict(); manifest); it lives in the tests only.
"""

from __future__ import annotations

import contextlib
import queue
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass

import cv2
import numpy as np
import zenoh

from aefabmap_runtime.errors import InputError
from aefabmap_runtime.adapters.zenoh_transport import (
    FramePublisher,
    SessionConfig,
    open_session,
    result_key_for,
    stats_key_for,
)
from aefabmap_runtime.core.detector import FrameResult
from aefabmap_runtime.tools.node_process import free_tcp_port

#: The image key the stream tests publish on, and the node's result / stats keys for it.
KEY = "robot/camera/image"
RESULTS = result_key_for(KEY)
STATS = stats_key_for(RESULTS)


def session_pair() -> tuple[SessionConfig, SessionConfig]:
    """(listener, connector) session configs on a fresh loopback port, scouting off."""
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    return SessionConfig(listen=(ep,)), SessionConfig(connect=(ep,))


class FakeDetector:
    """Deterministic stand-in: places are 16x12 thumbnails; a frame is a loop closure when
    its thumbnail is within ``threshold`` (mean abs gray difference) of a stored place,
    otherwise it becomes a new place at once (no delayed insertion).

    delay_s simulates a slow core (seconds per frame).
    """

    def __init__(self, threshold: float = 12.0, delay_s: float = 0.0) -> None:
        self.threshold = threshold
        self.delay_s = delay_s
        self.places: list[np.ndarray] = []
        self.place_frames: list[int] = []
        self.sequence = 0
        self.manifest = {"format_version": 1, "detector": "fake", "threshold": threshold}

    def process(self, gray: np.ndarray, stamp_ns: int) -> FrameResult:
        t0 = time.perf_counter()
        if gray.ndim != 2 or gray.shape[0] < 8 or gray.shape[1] < 8:
            raise InputError(f"image of shape {gray.shape} is too small")
        if self.delay_s:
            time.sleep(self.delay_s)  # simulated compute cost, not a wait
        thumb = cv2.resize(gray, (16, 12), interpolation=cv2.INTER_AREA).astype(np.float32)
        dists = [float(np.abs(thumb - p).mean()) for p in self.places]
        best = int(np.argmin(dists)) if dists else None
        best_d = dists[best] if best is not None else 255.0
        loop = best is not None and best_d < self.threshold
        inserted = None
        if not loop:
            inserted = len(self.places)
            self.places.append(thumb)
            self.place_frames.append(self.sequence)
        res = FrameResult(
            sequence=self.sequence,
            stamp_ns=int(stamp_ns),
            n_keypoints=int(gray.mean()),
            n_words=int(gray.std()),
            best_place=best,
            best_frame=self.place_frames[best] if best is not None else None,
            score=float(1.0 - best_d / 255.0),
            p_new=float(min(1.0, best_d / 255.0 * 4)),
            loop=bool(loop),
            inserted_frame=self.sequence if inserted is not None else None,
            inserted_place=inserted,
            n_places=len(self.places),
            timings_ms={"total": (time.perf_counter() - t0) * 1e3},
        )
        self.sequence += 1
        return res


def make_result(sequence: int, stamp_ns: int, **fields) -> FrameResult:
    """A minimal valid result record (what a log test writes on the results topic)."""
    base = dict(n_keypoints=0, n_words=0, best_place=None, best_frame=None, score=0.0, p_new=0.5, loop=False)
    return FrameResult(sequence=sequence, stamp_ns=stamp_ns, **{**base, **fields})


class JsonCollector:
    """Callback subscriber collecting the JSON docs of a key into a queue, each validated by its
    message parser first (StatsMessage for a ``.../stats`` key, else FrameResult); a message
    that fails validation is kept in ``invalid`` and fails the next wait_for."""

    def __init__(self, session: zenoh.Session, key: str) -> None:
        import json

        from aefabmap_runtime.core.records.messages import StatsMessage

        kind = StatsMessage if key.endswith("/stats") else FrameResult
        self.queue: queue.Queue = queue.Queue()
        self.invalid: list[str] = []

        def on_sample(sample) -> None:
            data = sample.payload.to_bytes()
            try:
                kind.from_json(data)
            except InputError as exc:
                self.invalid.append(str(exc))
                return
            self.queue.put(json.loads(data))

        self._sub = session.declare_subscriber(key, on_sample)

    def wait_for(self, predicate, timeout_s: float) -> list[dict]:
        """Collect docs until predicate(doc) is true for one of them; returns all docs seen."""
        seen = []
        deadline = time.monotonic() + timeout_s
        while True:
            assert not self.invalid, f"invalid messages: {self.invalid[:3]}"
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise AssertionError(f"timed out after {timeout_s} s; got {len(seen)} docs: {seen[-3:]}")
            try:
                doc = self.queue.get(timeout=remaining)
            except queue.Empty:
                continue
            seen.append(doc)
            if predicate(doc):
                return seen

    def close(self) -> None:
        self._sub.undeclare()


class NodeThread:
    """Runs run_node in a thread; .summary / .error after join."""

    def __init__(self, detector, session_config, *, view=None, snapshotter=None, **options) -> None:
        from aefabmap_runtime.adapters.node import NodeOptions, run_node

        self.stop = threading.Event()
        self.ready = threading.Event()
        self.summary = None
        self.error: BaseException | None = None

        def target() -> None:
            try:
                self.summary = run_node(detector, NodeOptions(session=session_config, **options),
                                        stop_event=self.stop, ready_event=self.ready, view=view,
                                        snapshotter=snapshotter)
            except BaseException as exc:  # reported to the test
                self.error = exc
            finally:
                self.ready.set()

        self.thread = threading.Thread(target=target, daemon=True)

    def __enter__(self) -> "NodeThread":
        self.thread.start()
        assert self.ready.wait(10), "node did not become ready"
        if self.error is not None:
            raise self.error
        return self

    def finish(self, timeout_s: float = 10.0):
        self.stop.set()
        self.thread.join(timeout_s)
        assert not self.thread.is_alive(), "node did not stop"
        if self.error is not None:
            raise self.error
        return self.summary

    def __exit__(self, *exc) -> None:
        self.stop.set()
        self.thread.join(10)


def sample_images(n: int, size=(160, 120), seed: int = 0) -> list[np.ndarray]:
    from aefabmap_runtime.tools.synthetic_route import generate_loop_sequence

    images, _ = generate_loop_sequence(max(n, 4), seed, size)
    return images[:n]


ROS2_HEADER_DEFS = """
================================================================================
MSG: std_msgs/Header
builtin_interfaces/Time stamp
string frame_id
================================================================================
MSG: builtin_interfaces/Time
int32 sec
uint32 nanosec
"""
ROS2_COMPRESSED_IMAGE = "std_msgs/Header header\nstring format\nuint8[] data\n" + ROS2_HEADER_DEFS
ROS2_IMAGE = (
    "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\nuint8 is_bigendian\n"
    "uint32 step\nuint8[] data\n" + ROS2_HEADER_DEFS
)


def record_live_log(path, **node_options):
    """A log at ``path`` recorded by a live node (NodeThread with a FakeDetector, loopback Zenoh):
    16 sample frames published as 8 JPEG then 8 raw mono8, every result awaited. node_options go
    to the NodeThread (stats_period_s, log_config, run_config...). Returns (summary, images)."""
    from aefabmap_runtime.tools.publisher import array_source, publish_frames

    images = sample_images(16, size=(96, 72))
    listen, connect = session_pair()
    with NodeThread(detector=FakeDetector(), session_config=listen, key=KEY, mcap_path=path, queue_size=32,
                    **node_options) as node:
        with open_session(connect) as s:
            results = JsonCollector(s, RESULTS)
            publish_frames(connect, KEY, array_source(images[:8], "jpeg"), rate_hz=200, wait_for_subscriber_s=10)
            publish_frames(connect, KEY, array_source(images[8:], "mono8"), rate_hz=200, wait_for_subscriber_s=10)
            results.wait_for(lambda d: d["sequence"] == 15, timeout_s=30)
            results.close()
        summary = node.finish()
    return summary, images


def write_ros2_bag(path, images, *, stamp0_ns: int = 1_700_000_000_000_000_000, raw_topic: bool = True,
                   pad: int = 3) -> list[int]:
    """Write a ROS 2 bag with /cam/compressed (jpeg CompressedImage) and, if raw_topic,
    /cam/raw (mono8 Image rows padded by ``pad`` bytes). Returns the stamps (ns)."""
    from mcap_ros2.writer import Writer as Ros2Writer

    stamps = []
    with open(path, "wb") as f:
        w = Ros2Writer(f)
        cschema = w.register_msgdef("sensor_msgs/msg/CompressedImage", ROS2_COMPRESSED_IMAGE)
        rschema = w.register_msgdef("sensor_msgs/msg/Image", ROS2_IMAGE)
        for i, img in enumerate(images):
            stamp = stamp0_ns + i * 100_000_000
            stamps.append(stamp)
            header = {"stamp": {"sec": stamp // 1_000_000_000, "nanosec": stamp % 1_000_000_000}, "frame_id": "cam"}
            ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 95])
            w.write_message("/cam/compressed", cschema, {"header": header, "format": "jpeg", "data": buf.tobytes()},
                            log_time=stamp, publish_time=stamp)
            if raw_topic:
                h, wd = img.shape
                padded = np.zeros((h, wd + pad), np.uint8)
                padded[:, :wd] = img
                msg = {"header": header, "height": h, "width": wd, "encoding": "mono8", "is_bigendian": 0,
                       "step": wd + pad, "data": padded.tobytes()}
                w.write_message("/cam/raw", rschema, msg, log_time=stamp + 1, publish_time=stamp)
        w.finish()
    return stamps


@contextlib.contextmanager
def mounted_tmpfs(directory, size: str = "1m"):
    """Mount a tmpfs of ``size`` on the (existing, empty) ``directory`` for the block: a real
    small disk to fill. Skips the test where it cannot be mounted (not root, no mount)."""
    import os
    import shutil
    import subprocess

    import pytest

    if os.geteuid() != 0 or shutil.which("mount") is None:
        pytest.skip("needs root to mount a tmpfs")
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(directory)],
                          capture_output=True, timeout=10, check=False)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs: {done.stderr.decode(errors='replace').strip()[:80]}")
    try:
        yield directory
    finally:
        subprocess.run(["umount", str(directory)], capture_output=True, timeout=10, check=False)


#: The command line of the package, as a child process runs it.
CLI = [sys.executable, "-m", "aefabmap.cli.main"]


@dataclass
class NodeRun:
    """What `run_node_process` saw: the results collected (up to the awaited sequence), the
    publisher's stdout, and the node's stdout, stderr and exit code after SIGTERM."""

    results: list[dict]
    published: str
    stdout: str
    stderr: str
    returncode: int


def run_node_process(run_args: list[str], images_dir, last_seq: int, *, rate: int = 30,
                     timeout_s: float = 90.0, stop_signal: int = signal.SIGTERM) -> NodeRun:
    """Start `aefabmap run RUN_ARGS --key KEY --listen EP` as a child process, feed it the images of
    images_dir with `aefabmap publish` once it subscribed, wait for the result of sequence
    last_seq, then stop it with stop_signal (SIGTERM: killed if it does not exit; SIGKILL: a crash)."""
    listen, connect = session_pair()
    ep = listen.listen[0]
    run = subprocess.Popen(CLI + ["run", *run_args, "--key", KEY, "--listen", ep],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        with open_session(connect) as s:
            results = JsonCollector(s, RESULTS)
            probe = FramePublisher(s, KEY)
            assert probe.wait_for_subscriber(60), "the node never subscribed"
            probe.close()
            pub = subprocess.run(CLI + ["publish", "--images", str(images_dir), "--key", KEY, "--rate", str(rate),
                                        "--connect", ep], capture_output=True, text=True, timeout=60, check=False)
            assert pub.returncode == 0, pub.stderr
            docs = results.wait_for(lambda d: d["sequence"] == last_seq, timeout_s=timeout_s)
            results.close()
        run.send_signal(stop_signal)
        out, err = run.communicate(timeout=60)
    finally:
        if run.poll() is None:
            run.kill()
            run.wait(10)
    return NodeRun(docs, pub.stdout, out, err, run.returncode)
