"""The Foxglove live view: thumbnail store, a real WebSocket client on the live server, the log."""

from __future__ import annotations

import json
import struct
import time

import cv2
import numpy as np
import pytest
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations

from aefabmap_runtime.adapters.foxglove_view import (
    ANNOTATIONS_TOPIC,
    IMAGE_TOPIC,
    PLACE_IMAGE_TOPIC,
    RESULT_TOPIC,
    LiveView,
    LiveViewConfig,
    PlaceThumbnails,
)
from aefabmap_runtime.adapters.mcap_log import McapLogReader, McapLogWriter
from aefabmap_runtime.core.records.messages import Candidate, FrameResult


def _gray(seed: int, shape=(192, 240)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return cv2.GaussianBlur(rng.integers(0, 256, shape, dtype=np.uint8), (5, 5), 0)


def _result(seq: int, *, inserted: int | None = None, evicted: int | None = None, best: int | None = None,
            points: int = 0) -> FrameResult:
    cands = []
    if best is not None:
        pts = [[float(i), float(i + 1), 2.0 * i, 3.0] for i in range(points)]
        cands = [Candidate(place=best, frame=best, rank=0, checked=True, verified=points > 0, inliers=points,
                           inlier_points=pts or None)]
    return FrameResult(sequence=seq, stamp_ns=1_700_000_000_000_000_000 + seq * 10**8, n_keypoints=100,
                       n_words=50, best_place=best, best_frame=best, score=0.9 if best is not None else 0.0,
                       p_new=0.1, loop=points > 0, inserted_frame=None if inserted is None else seq,
                       inserted_place=inserted, evicted_place=evicted, n_places=seq + 1, candidates=cands,
                       verified_place=best if points else None, inliers=points)


def test_thumbnails_follow_the_map_and_stay_within_bytes():
    config = LiveViewConfig(thumb_px=64, max_bytes=3000)
    store = PlaceThumbnails(config)
    store.observe(_gray(0), _result(0, inserted=0))
    one = store.get(0)
    assert one is not None and cv2.imdecode(np.frombuffer(one, np.uint8), 0).shape == (51, 64)
    store.observe(_gray(1), _result(1, inserted=1, evicted=0))
    assert store.get(0) is None and store.get(1) is not None  # evicted with the map
    for i in range(2, 20):
        store.observe(_gray(i), _result(i, inserted=i))
    assert 0 < store.nbytes <= 3000 and store.get(19) is not None and store.get(2) is None  # oldest dropped
    store.observe(_gray(50), _result(20, inserted=19))  # an id reused: the new frame's thumbnail
    assert store.get(19) == store.thumbnail(_gray(50))


class _FoxgloveClient:
    """A plain Foxglove WebSocket protocol client (subprotocol foxglove.sdk.v1, which foxglove-sdk 0.30 speaks; the
    former foxglove.websocket.v1 has the same advertise/subscribe/message-data frames): advertise -> subscribe."""

    def __init__(self, port: int) -> None:
        import websocket  # websocket-client (dev extra)

        self.ws = websocket.create_connection(f"ws://127.0.0.1:{port}", timeout=5,
                                              subprotocols=["foxglove.sdk.v1"])
        self.channels: dict[str, dict] = {}
        self.received: dict[str, list[bytes]] = {}

    def wait_advertised(self, topics: set[str], timeout_s: float = 5.0) -> None:
        deadline = time.monotonic() + timeout_s
        while not topics <= set(self.channels) and time.monotonic() < deadline:
            msg = self.ws.recv()
            if isinstance(msg, str):
                doc = json.loads(msg)
                if doc.get("op") == "advertise":
                    self.channels.update({c["topic"]: c for c in doc["channels"]})
        assert topics <= set(self.channels), sorted(self.channels)

    def subscribe(self, topics) -> None:
        self.sub_topic = {i: t for i, t in enumerate(topics, 1)}
        subs = [{"id": i, "channelId": self.channels[t]["id"]} for i, t in self.sub_topic.items()]
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))

    def receive_until(self, topics: set[str], timeout_s: float = 5.0) -> None:
        deadline = time.monotonic() + timeout_s
        while not topics <= set(self.received) and time.monotonic() < deadline:
            msg = self.ws.recv()
            if isinstance(msg, bytes) and msg[:1] == b"\x01":  # message data: op, sub id, log time, payload
                sub_id, _log_time = struct.unpack_from("<IQ", msg, 1)
                self.received.setdefault(self.sub_topic[sub_id], []).append(msg[13:])


def test_live_server_serves_image_annotations_place_and_result(tmp_path):
    pytest.importorskip("foxglove")
    pytest.importorskip("websocket")
    from aefabmap_runtime.adapters.foxglove_view import FoxgloveServer

    view = LiveView(FoxgloveServer(port=0))
    client = _FoxgloveClient(view.server.port)
    try:
        topics = [IMAGE_TOPIC, ANNOTATIONS_TOPIC, PLACE_IMAGE_TOPIC, RESULT_TOPIC]
        client.wait_advertised(set(topics))
        assert client.channels[ANNOTATIONS_TOPIC]["schemaName"] == "foxglove.ImageAnnotations"
        client.subscribe(topics)
        deadline = time.monotonic() + 5
        while not view.server.subscribed(RESULT_TOPIC) and time.monotonic() < deadline:
            time.sleep(0.01)  # the server registers the subscription asynchronously
        first = _gray(0)
        _ok, jpeg = cv2.imencode(".jpg", first)
        view.on_frame(jpeg.tobytes(), "image/jpeg", first, _result(0, inserted=0))
        raw = _gray(1)
        view.on_frame(raw.tobytes(), "mono8;240x192", raw, _result(1, best=0, points=12))
        client.receive_until(set(topics))
    finally:
        client.ws.close()
        view.close()
    images = [CompressedImage.FromString(b) for b in client.received[IMAGE_TOPIC]]
    assert [m.format for m in images] == ["jpeg", "jpeg"]  # the raw frame encoded
    assert cv2.imdecode(np.frombuffer(images[1].data, np.uint8), 0).shape == (192, 240)
    notes = [ImageAnnotations.FromString(b) for b in client.received[ANNOTATIONS_TOPIC]]
    assert len(notes[-1].points) == 1 and len(notes[-1].points[0].points) == 12
    assert notes[-1].points[0].points[3].x == 3.0 and "LOOP place 0" in notes[-1].texts[0].text
    place = CompressedImage.FromString(client.received[PLACE_IMAGE_TOPIC][0])
    assert place.format == "jpeg" and max(cv2.imdecode(np.frombuffer(place.data, np.uint8), 0).shape) == 160
    assert FrameResult.from_json(client.received[RESULT_TOPIC][-1]).inliers == 12


def test_view_channels_in_the_log_keep_the_reader_working(tmp_path):
    path = tmp_path / "view.mcap"
    with McapLogWriter(path) as log:
        view = LiveView(log=log)
        for i, result in enumerate([_result(0, inserted=0), _result(1, best=0, points=5)]):
            gray = _gray(i)
            _ok, png = cv2.imencode(".png", gray)
            log.write_image(png.tobytes(), "image/png", result.stamp_ns, sequence=i, gray=gray)
            view.on_frame(png.tobytes(), "image/png", gray, result)
            log.write_result(result)
    reader = McapLogReader(path)
    frames = list(reader.frames())
    assert len(frames) == 2 and reader.status.image_topic == IMAGE_TOPIC
    assert reader.status.ignored_image_topics == []  # the place thumbnails are not a camera
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        topics = {ch.topic: s.name for s, ch, _m in make_reader(f).iter_messages()}
    assert topics[ANNOTATIONS_TOPIC] == "foxglove.ImageAnnotations"
    assert topics[PLACE_IMAGE_TOPIC] == "foxglove.CompressedImage"


def test_layout_names_only_served_topics_and_existing_fields():
    from pathlib import Path

    from aefabmap_runtime.adapters.foxglove_view import STATS_TOPIC
    from aefabmap_runtime.core.records.messages import StatsMessage

    doc = json.loads((Path(__file__).parents[3] / "deploy" / "foxglove_layout.json").read_text())
    fields = {RESULT_TOPIC: FrameResult.json_schema()["properties"], STATS_TOPIC: StatsMessage.json_schema()["properties"]}
    served = {IMAGE_TOPIC, ANNOTATIONS_TOPIC, PLACE_IMAGE_TOPIC, *fields}
    seen = set()
    for panel, config in doc["configById"].items():
        image = config.get("imageMode", {})
        for topic in [image.get("imageTopic"), *image.get("annotations", {}), config.get("topicPath")]:
            if topic:
                assert topic in served, (panel, topic)
                seen.add(topic)
        for path in config.get("paths", []):
            topic, _, field = path["value"].partition(".")
            assert field.split(".")[0] in fields[topic], (panel, path)
            seen.add(topic)
    assert seen == served


@pytest.mark.timeout(90)
def test_live_node_with_view_serves_a_client_and_logs_the_view(tmp_path):
    """run_node + LiveView: frames over Zenoh -> a Foxglove client gets image, annotations, result,
    stats; the run's MCAP log gets the annotations too."""
    pytest.importorskip("foxglove")
    pytest.importorskip("websocket")
    from aefabmap_runtime.adapters.foxglove_view import STATS_TOPIC, FoxgloveServer
    from aefabmap_runtime.adapters.zenoh_transport import open_session
    from aefabmap_runtime.tools.publisher import array_source, publish_frames

    from .stream_fakes import (
        FakeDetector,
        JsonCollector,
        NodeThread,
        sample_images,
        session_pair,
    )

    view = LiveView(FoxgloveServer(port=0))
    client = _FoxgloveClient(view.server.port)
    topics = [IMAGE_TOPIC, ANNOTATIONS_TOPIC, RESULT_TOPIC, STATS_TOPIC]
    try:
        client.wait_advertised(set(topics))
        client.subscribe(topics)
        deadline = time.monotonic() + 5
        while not all(view.server.subscribed(t) for t in topics) and time.monotonic() < deadline:
            time.sleep(0.01)  # the server registers the subscription asynchronously
        listen, connect = session_pair()
        path = tmp_path / "live.mcap"
        with NodeThread(detector=FakeDetector(), session_config=listen, key="robot/camera/image", mcap_path=path,
                        queue_size=32, stats_period_s=0.2, view=view) as node:
            with open_session(connect) as s:
                results = JsonCollector(s, "robot/camera/lcd")
                publish_frames(connect, "robot/camera/image", array_source(sample_images(6, size=(96, 72)), "jpeg"),
                               rate_hz=100, wait_for_subscriber_s=10)
                results.wait_for(lambda d: d["sequence"] == 5, timeout_s=30)
                results.close()
            client.receive_until(set(topics), timeout_s=10)
            summary = node.finish()
    finally:
        client.ws.close()
        view.close()
    assert summary.frames_processed == 6
    assert set(topics) <= set(client.received)
    assert CompressedImage.FromString(client.received[IMAGE_TOPIC][0]).format == "jpeg"
    assert FrameResult.from_json(client.received[RESULT_TOPIC][0]).sequence == 0
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        counts: dict[str, int] = {}
        for _s, ch, _m in make_reader(f).iter_messages():
            counts[ch.topic] = counts.get(ch.topic, 0) + 1
    assert counts[ANNOTATIONS_TOPIC] == 6 and counts[RESULT_TOPIC] == 6


def test_cli_replay_foxglove_keeps_inlier_points_and_logs_the_view(tmp_path, monkeypatch, capsys):
    pytest.importorskip("foxglove")

    from aefabmap.cli import replay as cli_replay
    from tests.conftest import cli_args, make_synthetic_bundle

    from .stream_fakes import sample_images

    bundle = make_synthetic_bundle(tmp_path / "bundle")
    src = tmp_path / "src.mcap"
    images = sample_images(12, size=(160, 120))
    with McapLogWriter(src) as log:
        for i, img in enumerate(images):
            _ok, png = cv2.imencode(".png", img)
            log.write_image(png.tobytes(), "image/png", 1_700_000_000_000_000_000 + i * 10**8, sequence=i)
    import aefabmap_runtime.adapters.bundle_reader as bundle_reader_mod

    configs, real_load = [], bundle_reader_mod.load_detector
    monkeypatch.setattr(bundle_reader_mod, "load_detector", lambda path, config: configs.append(config)
                        or real_load(path, config))
    out = tmp_path / "out.mcap"
    args = cli_args("replay", src, "--model", bundle, "--out", out, "--foxglove", "0")
    held = []  # the server is kept up after the replay until Ctrl-C: test_foxglove_replay.py
    from aefabmap_runtime.adapters import replay_builder

    monkeypatch.setattr(replay_builder, "serve_until_stopped", lambda view, fleet, stop: held.append(view.server.port))
    assert cli_replay.main(args) == 0
    assert len(held) == 1
    assert configs[0].verification.keep_inlier_points  # the view draws them
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["frames_processed"] == 12
    from mcap.reader import make_reader

    with open(out, "rb") as f:
        topics = [ch.topic for _s, ch, _m in make_reader(f).iter_messages()]
    assert topics.count(ANNOTATIONS_TOPIC) == 12

    monkeypatch.setitem(__import__("sys").modules, "foxglove", None)  # foxglove-sdk absent
    assert cli_replay.main(args) == 2  # ConfigError: one line, "install aefabmap[foxglove]"


# -- exposure: the view has no authentication, so it is served beyond loopback only on purpose -----

@pytest.mark.parametrize("host", ["0.0.0.0", "::", "", "192.168.1.20", "camera.lab"])
def test_a_view_other_hosts_reach_needs_allow_exposure(tmp_path, host):
    from aefabmap_runtime.adapters.node_builder import NodeIO
    from aefabmap_runtime.adapters.node_session import Endpoints
    from aefabmap_runtime.adapters.replay_builder import ReplayIO
    from aefabmap_runtime.errors import ConfigError

    with pytest.raises(ConfigError, match="--allow-exposure") as info:
        NodeIO(mcap=tmp_path / "x.mcap", key="k", foxglove_port=0, foxglove_host=host)
    assert "\n" not in str(info.value)
    with pytest.raises(ConfigError, match="--allow-exposure"):
        ReplayIO(logs=("x.mcap",), model="m", foxglove_port=0, foxglove_host=host)
    NodeIO(mcap=tmp_path / "x.mcap", key="k", foxglove_port=0, foxglove_host=host,
           endpoints=Endpoints(allow_exposure=True))
    ReplayIO(logs=("x.mcap",), model="m", foxglove_port=0, foxglove_host=host,
             endpoints=Endpoints(allow_exposure=True))


@pytest.mark.parametrize("host", ["127.0.0.1", "127.0.0.2", "localhost", "::1"])
def test_a_loopback_view_needs_nothing(tmp_path, host):
    from aefabmap_runtime.adapters.node_builder import NodeIO

    NodeIO(mcap=tmp_path / "x.mcap", key="k", foxglove_port=0, foxglove_host=host)
    NodeIO(mcap=tmp_path / "x.mcap", key="k", foxglove_host="0.0.0.0")  # no view: nothing served


def _run_cli(tmp_path, *extra: str):
    """`aefabmap run` of the shipped bundle with a live view on any free port, as a process; and
    the session config that reaches it."""
    import subprocess

    from aefabmap.cli.options import default_bundle

    from .stream_fakes import CLI, KEY, session_pair

    listen, connect = session_pair()
    return subprocess.Popen(CLI + ["run", "--model", str(default_bundle()), "--key", KEY, "--listen", listen.listen[0],
                                   "--mcap", str(tmp_path / "run.mcap"), "--foxglove", "0", *extra],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True), connect


def test_run_refuses_a_view_on_every_interface_without_allow_exposure(tmp_path):
    """The attack: `run --foxglove PORT --foxglove-host 0.0.0.0` served the camera to the network,
    with no flag and no warning."""
    run, _ = _run_cli(tmp_path, "--foxglove-host", "0.0.0.0")
    try:
        out, err = run.communicate(timeout=60)
    finally:
        if run.poll() is None:
            run.kill()
            run.wait(10)
    assert run.returncode == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "--allow-exposure" in lines[0] and "0.0.0.0" in lines[0], err
    assert not (tmp_path / "run.mcap").exists()


def test_run_with_allow_exposure_serves_the_view_and_warns_once(tmp_path):
    pytest.importorskip("foxglove")
    import queue
    import signal
    import threading

    from aefabmap_runtime.adapters.zenoh_transport import FramePublisher, open_session

    from .stream_fakes import KEY

    run, connect = _run_cli(tmp_path, "--foxglove-host", "0.0.0.0", "--allow-exposure")
    lines: queue.Queue = queue.Queue()
    reader = threading.Thread(target=lambda: [lines.put(x) for x in run.stderr], daemon=True)
    reader.start()
    try:
        with open_session(connect) as s:  # the node is up (its stop handlers too) once it subscribed
            probe = FramePublisher(s, KEY)
            assert probe.wait_for_subscriber(90), "the node never subscribed"
            probe.close()
        run.send_signal(signal.SIGTERM)
        run.wait(60)
    finally:
        if run.poll() is None:
            run.kill()
            run.wait(10)
    reader.join(10)
    seen = []
    while not lines.empty():
        seen.append(lines.get())
    assert run.returncode == 0, "".join(seen)
    assert any("Foxglove live view on ws://0.0.0.0:" in x for x in seen), seen
    warned = [x for x in seen if x.startswith("WARNING") and "Foxglove" in x]
    assert len(warned) == 1 and "--allow-exposure" in warned[0] and "0.0.0.0" in warned[0], seen
