"""`replay --foxglove` as a player: waits for the first viewer (--wait-viewer), plays at the recorded
pace (--rate), keeps serving at the end until stopped. The viewer is a plain client written from the
Foxglove WebSocket protocol spec (foxglove/ws-protocol docs/spec.md): advertise -> subscribe -> binary
message data."""

from __future__ import annotations

import json
import logging
import struct
import threading
import time

import cv2
import pytest

from aefabmap_runtime.errors import ConfigError, TransportError
from aefabmap_runtime.adapters.foxglove_view import IMAGE_TOPIC, RESULT_TOPIC
from aefabmap_runtime.adapters.mcap_log import McapLogWriter
from aefabmap_runtime.core.records.messages import FrameResult
from aefabmap_runtime.tools.node_process import free_tcp_port

from .stream_fakes import FakeDetector, sample_images
from tests.conftest import cli_args

pytestmark = [pytest.mark.timeout(120)]

STAMP0 = 1_700_000_000_000_000_000
#: What Lichtblick offers since it added foxglove.sdk.v1 (lichtblick-suite/lichtblick#819).
VIEWER_SUBPROTOCOLS = ["foxglove.websocket.v1", "foxglove.sdk.v1"]


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
        self.sub_topic: dict[int, str] = {}

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
                sub_id, _log_time = struct.unpack_from("<IQ", msg, 1)
                self.received.setdefault(self.sub_topic[sub_id], []).append(msg[13:])

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


def test_foxglove_sdk_takes_sdk_v1_and_refuses_a_websocket_v1_only_client():
    """What docs/streaming.md says about viewers: the SDK picks foxglove.sdk.v1 when offered and
    answers HTTP 400 to a client that offers only foxglove.websocket.v1 (older Lichtblick)."""
    pytest.importorskip("foxglove")
    websocket = pytest.importorskip("websocket")
    from aefabmap_runtime.adapters.foxglove_view import FoxgloveServer

    server = FoxgloveServer(port=0)
    try:
        viewer = _Viewer(server.port, subprotocols=VIEWER_SUBPROTOCOLS)
        assert viewer.ws.getsubprotocol() == "foxglove.sdk.v1"
        viewer.close()
        with pytest.raises(websocket.WebSocketBadStatusException) as refused:
            _Viewer(server.port, subprotocols=["foxglove.websocket.v1"])
        assert refused.value.status_code == 400
    finally:
        server.stop()


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
