"""The shipped Zenoh config with mutual TLS and access control (deploy/zenoh-tls-acl.json5), as two
processes on loopback: `aefabmap run` is the router; a camera, a viewer and a forger connect with
certificates made here. Results reach the viewer; a forged result, from a participant the CA signed
or from the viewer itself, never does; a certificate from another CA is not let in."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh

from aefabmap_runtime.adapters.frames import encode_frame
from aefabmap_runtime.adapters.zenoh_transport import FramePublisher, SessionConfig, session_exposure
from aefabmap_runtime.tools.node_process import free_tcp_port
from tests.runtime.adapters.stream_fakes import CLI, KEY, RESULTS, JsonCollector

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "scripts"))
from fleet_tls import make_certificates  # noqa: E402

CONFIG = Path(__file__).resolve().parents[2] / "deploy" / "zenoh-tls-acl.json5"
FORGED = -12345  # the forged result's sequence: no real frame has it

pytestmark = pytest.mark.skipif(shutil.which("openssl") is None, reason="needs the openssl command")


def client(d: Path, name: str, port: int, ca: str = "ca") -> zenoh.Session:
    """A client session that connects to the node with NAME's certificate (trusting CA)."""
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([f"tls/localhost:{port}"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("transport/link/tls", json.dumps({
        "root_ca_certificate": str(d / f"{ca}.pem"), "connect_certificate": str(d / f"{name}.pem"),
        "connect_private_key": str(d / f"{name}.key"), "enable_mtls": True}))
    return zenoh.open(conf)


def forged_result() -> bytes:
    return json.dumps({"sequence": FORGED, "stamp_ns": 0, "n_keypoints": 0, "n_words": 0, "best_place": 0,
                       "best_frame": 0, "score": 1.0, "p_new": 0.0, "loop": True, "verified": True}).encode()


@pytest.mark.timeout(180)
def test_only_the_node_publishes_results_and_only_certified_peers_get_in(tmp_path):
    from tests.conftest import make_synthetic_bundle

    d = tmp_path / "tls"
    d.mkdir()
    make_certificates(d, ("node", "camera", "viewer", "forger"))
    make_certificates(d, ("stranger",), ca="other")
    port = free_tcp_port()
    text = CONFIG.read_text().replace("/etc/aefabmap/tls/", f"{d}/").replace("tls/0.0.0.0:7447", f"tls/127.0.0.1:{port}")
    conf_file = tmp_path / "node.json5"
    conf_file.write_text(text)
    assert session_exposure(SessionConfig(config_file=str(conf_file))) == []  # mutual TLS: not exposed
    bundle = make_synthetic_bundle(tmp_path / "bundle")
    node = subprocess.Popen(CLI + ["run", "--model", str(bundle), "--key", KEY, "--config", str(conf_file),
                                   "--queue", "32", "--mcap", str(tmp_path / "run.mcap")], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    sessions = []
    try:
        deadline = time.monotonic() + 60
        while True:  # the node's TLS listener comes up after the bundle loads
            try:
                viewer = client(d, "viewer", port)
                break
            except zenoh.ZError:
                assert node.poll() is None and time.monotonic() < deadline, node.communicate(timeout=10)
                time.sleep(0.2)
        # Another viewer (same certificate name) and a participant the CA signed with no role: both try to
        # publish results. (A session's own subscriber would get its own puts locally: the watcher is separate.)
        camera, forger, other_viewer = client(d, "camera", port), client(d, "forger", port), client(d, "viewer", port)
        sessions += [viewer, camera, forger, other_viewer]
        results = JsonCollector(viewer, RESULTS)
        pub = FramePublisher(camera, KEY, congestion="block")
        assert pub.wait_for_subscriber(60), "the camera never saw the node's subscription"
        forger_pub, viewer_pub = forger.declare_publisher(RESULTS), other_viewer.declare_publisher(RESULTS)
        rng = np.random.default_rng(0)
        for i in range(8):
            payload, encoding = encode_frame(rng.integers(0, 255, (120, 160), dtype=np.uint8), "png")
            pub.put(payload, encoding)
            forger_pub.put(forged_result())
            viewer_pub.put(forged_result())
        # The forged results went out with the frames, on a shorter path (straight through the router): had
        # they been let through, they would be among what arrived before the last real result.
        docs = results.wait_for(lambda doc: doc["sequence"] == 7, timeout_s=60)
        assert [doc["sequence"] for doc in docs] == list(range(8))
        assert FORGED not in [doc["sequence"] for doc in _drain(results)]
        with pytest.raises(zenoh.ZError):
            sessions.append(client(d, "stranger", port, ca="other"))  # another CA: the handshake fails
        results.close()
    finally:
        for s in sessions:
            s.close()
        node.terminate()
        out, err = node.communicate(timeout=60)
    assert node.returncode == 0, err[-2000:]


def _drain(collector: JsonCollector) -> list[dict]:
    out = []
    while not collector.queue.empty():
        out.append(collector.queue.get_nowait())
    return out
