"""`replay --foxglove` as a player: waits for the first viewer (--wait-viewer), plays at the recorded
pace (--rate), keeps serving at the end until stopped. The viewer is a plain client written from the
Foxglove WebSocket protocol spec (foxglove/ws-protocol docs/spec.md): advertise -> subscribe -> binary
message data."""

from __future__ import annotations

import json
import logging
import signal
import socket
import struct
import subprocess
import sys
import threading
import time

import cv2
import pytest

from aefabmap_runtime.errors import ConfigError, TransportError
from aefabmap_runtime.adapters.foxglove_view import IMAGE_TOPIC, RESULT_TOPIC
from aefabmap_runtime.adapters.mcap_log import McapLogWriter
from aefabmap_runtime.core.records.messages import FrameResult, StatsMessage
from aefabmap_runtime.tools.node_process import free_tcp_port

from .stream_fakes import FakeDetector, sample_images
from tests.conftest import cli_args

pytestmark = [pytest.mark.timeout(120)]

STAMP0 = 1_700_000_000_000_000_000
#: What Lichtblick offers since it added foxglove.sdk.v1 (lichtblick-suite/lichtblick#819).
VIEWER_SUBPROTOCOLS = ["foxglove.websocket.v1", "foxglove.sdk.v1"]
#: What Lichtblick up to 1.21 and older Foxglove Studio offer.
V1_ONLY = ["foxglove.websocket.v1"]


def _log(path, n: int, gap_s: float):
    """An aefabmap log of n PNG frames whose capture stamps are gap_s apart."""
    with McapLogWriter(path) as log:
        for i, img in enumerate(sample_images(n, size=(96, 72))):
            _ok, png = cv2.imencode(".png", img)
            log.write_image(png.tobytes(), "image/png", STAMP0 + round(i * gap_s * 1e9), sequence=i)
    return path


class _Viewer:
    """A Foxglove WebSocket client: collects the message data of the topics it subscribed to."""

    def __init__(self, port: int, subprotocols=VIEWER_SUBPROTOCOLS, connect_within_s: float = 10.0) -> None:
        import websocket  # websocket-client (dev extra)

        deadline = time.monotonic() + connect_within_s
        while True:  # the server may still be starting on a slow machine
            try:
                self.ws = websocket.create_connection(f"ws://127.0.0.1:{port}", timeout=5, subprotocols=subprotocols)
                break
            except ConnectionRefusedError:
                if time.monotonic() > deadline:
                    raise
                threading.Event().wait(0.1)
        self.channels: dict[str, dict] = {}
        self.received: dict[str, list[bytes]] = {}
        self.log_times: dict[str, list[int]] = {}
        self.sub_topic: dict[int, str] = {}
        self.first = self.ws.recv()  # the spec: serverInfo comes first

    def subscribe(self, topics: list[str], timeout_s: float = 10.0) -> None:
        """Wait for the topics' advertisement, then subscribe to them in one message."""
        deadline = time.monotonic() + timeout_s
        while not set(topics) <= set(self.channels) and time.monotonic() < deadline:
            msg = self.ws.recv()
            if isinstance(msg, str) and (doc := json.loads(msg)).get("op") == "advertise":
                self.channels.update({c["topic"]: c for c in doc["channels"]})
        assert set(topics) <= set(self.channels), sorted(self.channels)
        self.sub_topic = dict(enumerate(topics, 1))
        subs = [{"id": i, "channelId": self.channels[t]["id"]} for i, t in self.sub_topic.items()]
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))

    def receive_until(self, done, timeout_s: float) -> None:
        """Collect message data until ``done(received)`` or the timeout."""
        import websocket

        deadline = time.monotonic() + timeout_s
        while not done(self.received) and time.monotonic() < deadline:
            try:
                msg = self.ws.recv()
            except websocket.WebSocketTimeoutException:
                continue
            if isinstance(msg, bytes) and msg[:1] == b"\x01":  # op, subscription id u32, log time u64, payload
                sub_id, log_time = struct.unpack_from("<IQ", msg, 1)
                self.received.setdefault(self.sub_topic[sub_id], []).append(msg[13:])
                self.log_times.setdefault(self.sub_topic[sub_id], []).append(log_time)

    def close(self) -> None:
        self.ws.close()


class _ReplayCli(threading.Thread):
    """`aefabmap replay ...` through the CLI's main, in a thread, stopped by ``self.stop``."""

    def __init__(self, argv) -> None:
        super().__init__(daemon=True)
        self.args, self.stop, self.code = cli_args("replay", *argv), threading.Event(), None

    def run(self) -> None:
        from aefabmap.cli import replay as cli_replay

        self.code = cli_replay.main(self.args, stop=self.stop)


@pytest.fixture
def fake_detector(monkeypatch):
    import aefabmap_runtime.adapters.bundle_reader as bundle_reader_mod

    monkeypatch.setattr(bundle_reader_mod, "load_detector", lambda *a, **k: FakeDetector())


@pytest.fixture
def holding(monkeypatch):
    """Set once the replay starts serving after it (the real serve_until_stopped still runs)."""
    from aefabmap_runtime.adapters import replay_builder

    event, real = threading.Event(), replay_builder.serve_until_stopped
    monkeypatch.setattr(replay_builder, "serve_until_stopped", lambda view, fleet, stop: (event.set(), real(view, fleet, stop)))
    return event


def test_a_late_viewer_receives_every_frame_and_the_server_stays_up(tmp_path, fake_detector, holding, caplog,
                                                                     capsys):
    """The issue's must-show with a shorter delay: a viewer connecting 2 s after
    `replay --foxglove PORT --wait-viewer` started gets every frame's image and result."""
    pytest.importorskip("foxglove")
    pytest.importorskip("websocket")
    caplog.set_level(logging.INFO)
    n, port = 12, free_tcp_port()
    src = _log(tmp_path / "src.mcap", n, gap_s=0.05)
    cli = _ReplayCli([src, "--model", "fake", "--foxglove", str(port), "--wait-viewer", "60"])
    cli.start()
    viewer = None
    try:
        assert not holding.wait(2.0)  # the viewer comes late; the replay must not have run meanwhile
        viewer = _Viewer(port)
        viewer.subscribe([IMAGE_TOPIC, RESULT_TOPIC])
        viewer.receive_until(lambda got: len(got.get(RESULT_TOPIC, [])) >= n and len(got.get(IMAGE_TOPIC, [])) >= n,
                             timeout_s=30)
        assert holding.wait(30)  # the replay ended, the server is kept up
        assert cli.is_alive()
        late = _Viewer(port)  # still served: a new viewer gets the channels advertised
        late.subscribe([RESULT_TOPIC])
        late.close()
    finally:
        if viewer is not None:
            viewer.close()
        cli.stop.set()  # what Ctrl-C/SIGTERM does
        cli.join(10)
    assert not cli.is_alive() and cli.code == 0
    sequences = [FrameResult.from_json(b).sequence for b in viewer.received[RESULT_TOPIC]]
    assert sequences == list(range(n))
    assert len(viewer.received[IMAGE_TOPIC]) == n
    assert "Foxglove server still up" in caplog.text
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["frames_processed"] == n


def test_no_viewer_in_time_is_a_one_line_error(tmp_path, fake_detector, caplog):
    pytest.importorskip("foxglove")
    src = _log(tmp_path / "src.mcap", 3, gap_s=0.05)
    cli = _ReplayCli([src, "--model", "fake", "--foxglove", "0", "--wait-viewer", "0.3"])
    cli.run()  # in this thread: it returns after the timeout
    assert cli.code == TransportError.exit_code
    errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1 and "no Foxglove viewer subscribed" in errors[0] and "\n" not in errors[0]


@pytest.mark.parametrize("argv", [
    ["--rate", "-1"], ["--rate", "nan"], ["--rate", "inf"], ["--wait-viewer", "5"],
    ["--foxglove", "0", "--wait-viewer", "0"],
])
def test_bad_playback_options_are_one_line_errors(tmp_path, fake_detector, caplog, argv):
    src = _log(tmp_path / "src.mcap", 2, gap_s=0.05)
    cli = _ReplayCli([src, "--model", "fake", *argv])
    cli.run()
    assert cli.code == ConfigError.exit_code
    errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1 and "\n" not in errors[0], errors


def test_library_wait_for_a_viewer_needs_a_view_and_stops_on_the_event(tmp_path):
    pytest.importorskip("foxglove")
    from aefabmap_runtime.adapters.foxglove_view import FoxgloveServer, LiveView
    from aefabmap_runtime.adapters.replay import PlaybackConfig, replay

    src = _log(tmp_path / "src.mcap", 3, gap_s=0.05)
    with pytest.raises(ConfigError, match="viewer"):
        replay(FakeDetector(), src, playback=PlaybackConfig(wait_viewer_s=1))
    view = LiveView(FoxgloveServer(port=0))
    try:
        stop = threading.Event()
        threading.Timer(0.3, stop.set).start()  # Ctrl-C while waiting for a viewer
        t0 = time.monotonic()
        summary = replay(FakeDetector(), src, view=view, playback=PlaybackConfig(rate=1, wait_viewer_s=60), stop=stop)
        assert time.monotonic() - t0 < 30 and summary.stopped and summary.frames_processed == 0
    finally:
        view.close()


def test_one_port_takes_both_subprotocols_and_refuses_others():
    """What docs/streaming.md says about viewers: sdk.v1 when offered (the SDK's server), the
    older foxglove.websocket.v1 alone (Lichtblick up to 1.21) too, and HTTP 400 to a client that
    offers neither."""
    pytest.importorskip("foxglove")
    pytest.importorskip("foxglove_websocket")
    websocket = pytest.importorskip("websocket")
    from aefabmap_runtime.adapters.foxglove_view import FoxgloveServer

    server = FoxgloveServer(port=0)
    try:
        for offered, chosen in ((VIEWER_SUBPROTOCOLS, "foxglove.sdk.v1"), (V1_ONLY, "foxglove.websocket.v1")):
            viewer = _Viewer(server.port, subprotocols=offered)
            assert viewer.ws.getsubprotocol() == chosen
            assert json.loads(viewer.first)["op"] == "serverInfo"
            viewer.close()
        with pytest.raises(websocket.WebSocketBadStatusException) as refused:
            _Viewer(server.port, subprotocols=["something.else"])
        assert refused.value.status_code == 400
    finally:
        server.stop()


def test_without_foxglove_websocket_sdk_viewers_are_served_and_a_warning_says_who_is_not(monkeypatch, caplog):
    pytest.importorskip("foxglove")
    websocket = pytest.importorskip("websocket")
    from aefabmap_runtime.adapters.foxglove_view import FoxgloveServer

    for name in ("foxglove_websocket", "foxglove_websocket.server"):
        monkeypatch.setitem(sys.modules, name, None)  # not installed
    server = FoxgloveServer(port=0)
    try:
        warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
        assert len(warned) == 1 and "foxglove.websocket.v1" in warned[0] and "aefabmap[foxglove]" in warned[0]
        viewer = _Viewer(server.port)
        viewer.subscribe([RESULT_TOPIC])
        viewer.close()
        with pytest.raises(websocket.WebSocketBadStatusException):
            _Viewer(server.port, subprotocols=V1_ONLY)
    finally:
        server.stop()


def test_a_viewer_speaking_only_websocket_v1_gets_the_replay(tmp_path, fake_detector, holding):
    """A client written from the ws-protocol spec, offering only foxglove.websocket.v1: it is the
    viewer --wait-viewer waits for, and it receives every result and the stats."""
    pytest.importorskip("foxglove")
    pytest.importorskip("foxglove_websocket")
    pytest.importorskip("websocket")
    from aefabmap_runtime.adapters.foxglove_view import STATS_TOPIC

    n, port = 8, free_tcp_port()
    src = _log(tmp_path / "src.mcap", n, gap_s=0.05)
    cli = _ReplayCli([src, "--model", "fake", "--foxglove", str(port), "--wait-viewer", "60"])
    cli.start()
    viewer = None
    try:
        viewer = _Viewer(port, subprotocols=V1_ONLY)
        assert viewer.ws.getsubprotocol() == "foxglove.websocket.v1"
        viewer.subscribe([RESULT_TOPIC, STATS_TOPIC])
        viewer.receive_until(lambda got: len(got.get(RESULT_TOPIC, [])) >= n and STATS_TOPIC in got, timeout_s=30)
        assert holding.wait(30)
    finally:
        if viewer is not None:
            viewer.close()
        cli.stop.set()
        cli.join(10)
    assert not cli.is_alive() and cli.code == 0
    assert [FrameResult.from_json(b).sequence for b in viewer.received[RESULT_TOPIC]] == list(range(n))
    assert StatsMessage.from_json(viewer.received[STATS_TOPIC][-1]).frames_processed == n


def test_the_port_closes_a_request_head_too_long_and_serves_the_next_viewer():
    """A hostile client: a request head past HEAD_LIMIT bytes is cut and counted, nothing raised."""
    pytest.importorskip("foxglove")
    pytest.importorskip("websocket")
    from aefabmap_runtime.adapters.foxglove_front import HEAD_LIMIT
    from aefabmap_runtime.adapters.foxglove_view import FoxgloveServer

    server = FoxgloveServer(port=0)
    try:
        with socket.create_connection(("127.0.0.1", server.port), timeout=10) as sock:
            sock.sendall(b"GET / HTTP/1.1\r\nX-Junk: " + b"a" * (HEAD_LIMIT + 10))
            assert _read_to_end(sock) == b""  # closed without an answer
        assert server.front.router.problems["long_request"] == 1
        viewer = _Viewer(server.port)
        viewer.subscribe([RESULT_TOPIC])
        viewer.close()
    finally:
        server.stop()


def _read_to_end(sock: socket.socket) -> bytes:
    data = b""
    try:
        while chunk := sock.recv(4096):
            data += chunk
    except ConnectionResetError:
        pass
    return data


def test_replay_sends_stats_on_lcd_stats_every_period_of_replay_time(tmp_path, fake_detector, holding):
    """`replay --foxglove` sends `run`'s StatsMessage on /lcd/stats: one each time the replayed
    capture stamps have advanced by the stats period (5 s, as `run`), and one at the end, each at
    the stamp of the frame that made it due, so the layout's fps and latency plots fill. At
    --rate 0 the 11 s of log take well under that: the cadence follows replay time, not the clock."""
    pytest.importorskip("foxglove")
    pytest.importorskip("websocket")
    from aefabmap_runtime.adapters.foxglove_view import STATS_TOPIC

    n, port = 12, free_tcp_port()
    src = _log(tmp_path / "src.mcap", n, gap_s=1.0)  # frame k at STAMP0 + k s
    cli = _ReplayCli([src, "--model", "fake", "--foxglove", str(port), "--wait-viewer", "60", "--rate", "0"])
    cli.start()
    viewer = None
    try:
        viewer = _Viewer(port)
        viewer.subscribe([STATS_TOPIC, RESULT_TOPIC])
        assert holding.wait(30)  # the replay ended: every message was sent
        viewer.receive_until(lambda got: len(got.get(STATS_TOPIC, [])) >= 3 and len(got.get(RESULT_TOPIC, [])) >= n,
                             timeout_s=10)
    finally:
        if viewer is not None:
            viewer.close()
        cli.stop.set()
        cli.join(10)
    assert cli.code == 0
    stats = [StatsMessage.from_json(b) for b in viewer.received[STATS_TOPIC]]
    assert viewer.log_times[STATS_TOPIC] == [STAMP0 + 5 * 10**9, STAMP0 + 10 * 10**9, STAMP0 + 11 * 10**9]
    assert [m.frames_processed for m in stats] == [6, 11, 12]
    assert all(m.fps is not None and m.fps > 0 for m in stats)
    assert all(m.latency_ms.p95 is not None and m.latency_ms.p95 >= m.latency_ms.p50 > 0 for m in stats)
    assert stats[-1].frames_received == n and stats[-1].uptime_s > 0


@pytest.mark.timeout(180)
def test_ctrl_c_while_waiting_for_a_viewer_exits_130(tmp_path):
    """`aefabmap replay --foxglove --wait-viewer` as a process, sent SIGINT while it waits: exit 130
    (interrupted, as --help says), the summary line still printed, no traceback."""
    pytest.importorskip("foxglove")
    from tests.conftest import make_synthetic_bundle

    from .stream_fakes import CLI

    bundle = make_synthetic_bundle(tmp_path / "bundle")
    src = _log(tmp_path / "src.mcap", 3, gap_s=0.05)
    proc = subprocess.Popen(CLI + ["replay", str(src), "--model", str(bundle), "--foxglove", "0", "--wait-viewer", "120"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    waiting, lines = threading.Event(), []

    def read_stderr() -> None:
        for line in proc.stderr:
            lines.append(line)
            if "waiting up to" in line:
                waiting.set()

    reader = threading.Thread(target=read_stderr, daemon=True)
    reader.start()
    try:
        assert waiting.wait(120), "".join(lines)
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    reader.join(10)
    assert proc.returncode == 130, "".join(lines)
    assert json.loads(out.strip().splitlines()[-1])["stopped"] is True
    assert "Traceback" not in "".join(lines)


def test_replay_serves_a_view_beyond_loopback_only_with_allow_exposure(tmp_path, fake_detector, caplog,
                                                                       monkeypatch):
    pytest.importorskip("foxglove")
    from aefabmap_runtime.adapters import replay_builder

    monkeypatch.setattr(replay_builder, "serve_until_stopped", lambda view, fleet, stop: None)
    src = _log(tmp_path / "src.mcap", 3, gap_s=0.01)
    cli = _ReplayCli([src, "--model", "fake", "--foxglove", "0", "--foxglove-host", "0.0.0.0", "--rate", "0"])
    cli.run()
    assert cli.code == ConfigError.exit_code
    errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1 and "--allow-exposure" in errors[0] and "\n" not in errors[0], errors

    caplog.clear()
    cli = _ReplayCli([src, "--model", "fake", "--foxglove", "0", "--foxglove-host", "0.0.0.0", "--rate", "0",
                      "--allow-exposure"])
    cli.run()
    assert cli.code == 0
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warned) == 1 and "--allow-exposure" in warned[0] and "Foxglove" in warned[0], warned
