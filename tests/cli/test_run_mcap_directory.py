"""`run --mcap DIR/`: a directory target that does not exist yet is created (README: `--mcap logs/`)."""

from __future__ import annotations

import time
from pathlib import Path

from aefabmap.cli.options import default_bundle
from aefabmap_runtime.adapters.log_set import MCAP_MAGIC
from aefabmap_runtime.adapters.zenoh_transport import FramePublisher, SessionConfig, open_session
from aefabmap_runtime.tools.node_process import free_tcp_port, start_run_node, stop_node

KEY = "test/camera/image"


def _wait_subscribed(endpoint: str, node, timeout_s: float) -> bool:
    """True once the node subscribed to KEY (it is running); False when it exited or timed out."""
    deadline = time.monotonic() + timeout_s
    with open_session(SessionConfig(connect=(endpoint,))) as session:
        probe = FramePublisher(session, KEY)
        try:
            while node.poll() is None and time.monotonic() < deadline:
                if probe.wait_for_subscriber(0.5):
                    return True
            return False
        finally:
            probe.close()


def test_run_creates_a_missing_log_directory_with_its_parents(tmp_path):
    logs = tmp_path / "logs" / "robot-1"  # neither exists
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    node = start_run_node(default_bundle(), KEY, endpoint, f"{logs}/", tmp_path / "node.err")
    try:
        subscribed = _wait_subscribed(endpoint, node, timeout_s=60.0)
    finally:
        summary = stop_node(node)
    err = (tmp_path / "node.err").read_text()
    assert subscribed and node.returncode == 0 and summary is not None, err
    written = Path(summary.mcap_path)
    assert written.parent == logs and written.name.startswith("lcd-"), summary.mcap_path
    assert written.read_bytes()[:len(MCAP_MAGIC)] == MCAP_MAGIC
