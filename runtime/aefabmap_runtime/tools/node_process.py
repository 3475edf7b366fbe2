"""Supervising an `aefabmap run` child process over loopback (demo, stream and soak benchmarks).

Adapter code: the benchmark's working directory, starts the node, connects to it once it
listens, stops it with SIGTERM and reads its JSON run summary.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Sequence
from pathlib import Path

from aefabmap_runtime.errors import InputError, TransportError
from aefabmap_runtime.core.records.messages import FrameResult, RunSummary, StatsMessage

#: Environment of a node with one BLAS/OpenMP thread (as deploy/aefabmap.service sets it).
SINGLE_THREAD_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def bench_workdir(workdir: str | Path | None, prefix: str) -> tuple[Path, tempfile.TemporaryDirectory | None]:
    """A benchmark's working directory: ``workdir`` (created if missing), or a new temporary
    directory named ``prefix...`` when None. Returns (path, the temporary directory to clean up,
    or None for a given workdir, which is kept)."""
    if workdir is None:
        tmp = tempfile.TemporaryDirectory(prefix=prefix)
        return Path(tmp.name), tmp
    path = Path(workdir)
    path.mkdir(parents=True, exist_ok=True)
    return path, None


def free_tcp_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def start_run_node(bundle: str | Path, key: str, endpoint: str, mcap: str | Path, stderr_path: Path,
                   extra_args: Sequence[str] = (), node_threads: int | None = 1) -> subprocess.Popen:
    """Start ``aefabmap run --model bundle --key key --listen endpoint --mcap mcap *extra_args``
    as a child (stdout piped for its run summary, stderr to stderr_path). node_threads: the
    child's OMP/OPENBLAS/MKL_NUM_THREADS (None: inherit this environment)."""
    cmd = [sys.executable, "-m", "aefabmap.cli.main", "run", "--model", str(bundle), "--key", key,
           "--listen", endpoint, "--mcap", str(mcap), *extra_args]
    env = dict(os.environ)
    if node_threads is not None:
        env.update({k: str(node_threads) for k in SINGLE_THREAD_ENV})
    err = open(stderr_path, "w")  # noqa: SIM115 - the child holds its own descriptor
    try:
        return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=err, text=True, env=env)
    finally:
        err.close()


def process_rss_mb(pid: int | str) -> float | None:
    """VmRSS of a process in MB from /proc/<pid>/status (pid "self": this one; None when unavailable)."""
    try:
        with open(f"/proc/{pid}/status", encoding="ascii", errors="replace") as f:
            return rss_mb_of_status(f.read())
    except OSError:
        return None


def rss_mb_of_status(text: str) -> float | None:
    """VmRSS in MB of the text of a /proc/<pid>/status file; None without a positive one (a
    process in the middle of exec, or exiting, reports 0 kB: its memory, not yet or no longer)."""
    for line in text.splitlines():
        if line.startswith("VmRSS:"):
            try:
                kb = int(line.split()[1])
            except (ValueError, IndexError):
                return None
            return kb / 1024.0 if kb > 0 else None
    return None


def connect_when_listening(endpoint: str, node: subprocess.Popen, timeout_s: float):
    """Open a Zenoh session to a starting node's endpoint; fails fast if the node exits."""
    from aefabmap_runtime.adapters.zenoh_transport import SessionConfig, open_session

    deadline = time.monotonic() + timeout_s
    sc = SessionConfig(connect=(endpoint,))
    gate = threading.Event()
    while True:
        if node.poll() is not None:
            raise TransportError(f"the runtime node exited early with code {node.returncode}")
        try:
            return open_session(sc)
        except TransportError:
            if time.monotonic() > deadline:
                raise
            gate.wait(0.2)  # the node is starting: there is no event to wait on


def stop_node(node: subprocess.Popen, timeout_s: float = 30.0) -> RunSummary | None:
    """SIGTERM the node, wait for it (kill after timeout_s) and return its run summary
    (the last stdout line that parses as one; None when there is none)."""
    if node.poll() is None:
        node.send_signal(signal.SIGTERM)
    try:
        stdout, _ = node.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        node.kill()
        stdout, _ = node.communicate()
    for line in reversed((stdout or "").splitlines()):
        try:
            return RunSummary.from_json(line)
        except InputError:
            continue
    return None


class ResultCollector:
    """The node's results and stats as they arrive (zenoh callback threads), counted and waited on.

    Subclasses keep what they need of each message (`_keep_result`, `_keep_stats`, called
    under `cond`); messages that fail validation are counted in `invalid`.
    """

    def __init__(self) -> None:
        self.cond = threading.Condition()
        self.processed = 0
        self.invalid = 0
        self.last_recv = time.monotonic()

    def _keep_result(self, res: FrameResult, recv_ns: int) -> None:
        pass

    def _keep_stats(self, msg: StatsMessage) -> None:
        pass

    def on_result(self, sample) -> None:
        recv_ns = time.time_ns()
        try:
            res = FrameResult.from_json(sample.payload.to_bytes())
        except InputError:
            self.invalid += 1
            return
        with self.cond:
            self.processed += 1
            self._keep_result(res, recv_ns)
            self.last_recv = time.monotonic()
            self.cond.notify_all()

    def on_stats(self, sample) -> None:
        try:
            msg = StatsMessage.from_json(sample.payload.to_bytes())
        except InputError:
            self.invalid += 1
            return
        with self.cond:
            self._keep_stats(msg)

    def count(self) -> int:
        with self.cond:
            return self.processed

    def wait_processed(self, n: int, timeout_s: float) -> bool:
        with self.cond:
            return self.cond.wait_for(lambda: self.processed >= n, timeout_s)

    def drain(self, expected: int, idle_s: float, max_s: float) -> None:
        """Wait until `expected` results came or none for idle_s (at most max_s)."""
        deadline = time.monotonic() + max_s
        with self.cond:
            while self.processed < expected:
                left = min(self.last_recv + idle_s, deadline) - time.monotonic()
                if left <= 0:
                    return
                self.cond.wait(left)
