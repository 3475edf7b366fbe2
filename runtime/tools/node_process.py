"""Supervising an `aefabmap run` child process over loopback (demo, stream benchmark).

Adapter code: starts the node, connects to it once it listens, stops it with SIGTERM and
reads its JSON run summary.
"""

from __future__ import annotations

import signal
import socket
import subprocess
import threading
import time

from aefabmap.errors import InputError, TransportError
from aefabmap.runtime.core.messages import RunSummary


def free_tcp_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def connect_when_listening(endpoint: str, node: subprocess.Popen, timeout_s: float):
    """Open a Zenoh session to a starting node's endpoint; fails fast if the node exits."""
    from aefabmap.runtime.adapters.zenoh_transport import SessionConfig, open_session

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
