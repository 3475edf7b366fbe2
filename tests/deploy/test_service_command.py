"""The unit's own command line, run as the unit would (its seccomp filters included): it starts
before the local Zenoh router exists, connects when it appears, processes frames, logs every 30th
image, and on SIGTERM finishes the log and prints its summary."""

from __future__ import annotations

import json
import os
import queue
import signal
import socket
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from aefabmap.cli.demo import default_bundle
from aefabmap_runtime.tools.synthetic_route import make_demo_sequence
from tests.deploy.unit_file import (
    REPO,
    read_unit,
    run_argv,
    sandbox_available,
    sandbox_prefix,
)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _unit_argv(model: Path, mcap: Path, router_port: int) -> list[str]:
    """ExecStart's `aefabmap run` arguments with the board's paths and router port replaced."""
    argv = run_argv(read_unit()["Service"])
    replace = {"--model": str(model), "--mcap": str(mcap), "--connect": f"tcp/127.0.0.1:{router_port}"}
    return [replace.get(argv[i - 1], a) if i else a for i, a in enumerate(argv)]


@pytest.mark.slow
@pytest.mark.timeout(300)
@pytest.mark.skipif(not sandbox_available(), reason="needs Linux, libseccomp and systemd-analyze")
def test_unit_command_runs_against_a_local_router(tmp_path):
    frames = tmp_path / "frames"
    make_demo_sequence(frames, n_frames=30, seed=3, size=(320, 240))
    port = _free_port()
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")])),
           "OMP_NUM_THREADS": "1"}
    mcap = tmp_path / "lcd.mcap"
    runtime = subprocess.Popen(
        [*sandbox_prefix(read_unit()["Service"]), sys.executable, "-m", "aefabmap.cli.main",
         *_unit_argv(default_bundle(), mcap, port)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
    )
    lines: queue.Queue[str] = queue.Queue()
    log: list[str] = []

    def read_stderr() -> None:
        for line in runtime.stderr:
            log.append(line)
            lines.put(line)

    reader = threading.Thread(target=read_stderr, daemon=True)
    reader.start()
    try:
        # The first stats line means the bundle is loaded and the subscriber declared.
        while "aefabmap.run: processed" not in lines.get(timeout=120):
            pass
        # Stand-in for the local router: a publisher listening on its port. The runtime keeps
        # retrying its --connect, so it must find it; --loop/--count give it ~10 s to do so.
        pub = subprocess.run(
            [sys.executable, "-m", "aefabmap.cli.main", "publish", "--images", str(frames), "--key",
             "robot/camera/image", "--rate", "15", "--loop", "--count", "150", "--listen", f"tcp/127.0.0.1:{port}"],
            check=False, capture_output=True, text=True, timeout=120, env=env,
        )
        assert pub.returncode == 0, pub.stderr[-2000:]
    finally:
        runtime.send_signal(signal.SIGTERM)
        runtime.wait(timeout=60)
        reader.join(timeout=10)
    assert runtime.returncode == 0, "".join(log)[-3000:]
    summary = json.loads(runtime.stdout.read().strip().splitlines()[-1])
    print("unit command:", {k: summary[k] for k in ("frames_received", "frames_processed", "images_logged", "loops")})
    assert summary["frames_processed"] >= 30, summary
    # --image-every 30: one logged image per 30 frames received.
    assert 1 <= summary["images_logged"] <= summary["frames_received"] // 30 + 1, summary
    assert mcap.stat().st_size > 0
    # Under the unit numba's JIT cannot run (or numba is absent): the log names the kernels that
    # do, the ahead-of-time compiled ones where they are built.
    from aefabmap_runtime.core.kernels import native

    expected = "kernels: native" if native.available() else "kernels: numpy / OpenCV"
    assert any(expected in line for line in log), "".join(log)[-3000:]
