"""Zenoh adapters on real loopback sessions (runtime/aefabmap_runtime/adapters/zenoh_transport.py)."""

from __future__ import annotations

import dataclasses
import json
import re
import threading

import pytest
import zenoh

from aefabmap_runtime.errors import ConfigError, TransportError
from aefabmap_runtime.adapters.frames import encode_frame
from aefabmap_runtime.adapters.zenoh_transport import (
    DropCounter,
    FrameMeta,
    FramePublisher,
    FrameSubscriber,
    SessionConfig,
    build_zenoh_config,
    open_session,
    result_key_for,
    stats_key_for,
)
from aefabmap_runtime.tools.node_process import free_tcp_port

from .stream_fakes import sample_images, session_pair

pytestmark = pytest.mark.timeout(60)


def test_config_from_endpoints_turns_scouting_off():
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    conf = build_zenoh_config(SessionConfig(connect=(ep,), listen=("tcp/127.0.0.1:0",)))
    assert json.loads(conf.get_json("mode")) == "peer"
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    assert json.loads(conf.get_json("connect/endpoints")) == [ep]
    # comma-separated and repeated values both work
    sc = SessionConfig(connect=("tcp/127.0.0.1:1,tcp/127.0.0.1:2", "tcp/127.0.0.1:3"))
    assert sc.connect == ("tcp/127.0.0.1:1", "tcp/127.0.0.1:2", "tcp/127.0.0.1:3")


@pytest.mark.parametrize("bad", ["nonsense", "tcp/127.0.0.1", "tcp/127.0.0.1:abc", "tcp/127.0.0.1:70000"])
def test_bad_endpoint_is_config_error(bad):
    with pytest.raises(ConfigError):
        SessionConfig(connect=(bad,))


def test_bad_mode_and_config_file(tmp_path):
    with pytest.raises(ConfigError):
        SessionConfig(mode="server")
    with pytest.raises(ConfigError, match="does not exist"):
        build_zenoh_config(SessionConfig(config_file=str(tmp_path / "missing.json5")))
    bad = tmp_path / "bad.json5"
    bad.write_text("{ mode: 'wizard', }")
    with pytest.raises(ConfigError):
        build_zenoh_config(SessionConfig(config_file=str(bad)))
    good = tmp_path / "good.json5"
    good.write_text("{ mode: 'client', }")
    conf = build_zenoh_config(SessionConfig(config_file=str(good), listen=("tcp/127.0.0.1:0",)))
    assert json.loads(conf.get_json("mode")) == "client"  # no mode option given: the file's mode stands
    assert json.loads(conf.get_json("listen/endpoints")) == ["tcp/127.0.0.1:0"]  # explicit options override


def test_session_that_cannot_open_is_transport_error():
    listen, _ = session_pair()
    first = open_session(listen)
    try:
        with pytest.raises(TransportError, match="cannot open zenoh session"):
            open_session(listen)  # same port twice
    finally:
        first.close()


def test_result_keys():
    assert result_key_for("robot/camera/image") == "robot/camera/lcd"
    assert result_key_for("camera") == "lcd"
    assert result_key_for("robot/camera/*") == "robot/camera/lcd"
    assert stats_key_for("robot/camera/lcd") == "robot/camera/lcd/stats"
    with pytest.raises(ConfigError):
        result_key_for("robot/*/image")
    with pytest.raises(ConfigError):
        result_key_for("robot/lcd")


def test_frame_meta_and_drop_counter():
    meta = FrameMeta(seq=3, stamp_ns=42, src="a")
    assert FrameMeta.from_attachment(meta.to_attachment()) == meta
    assert FrameMeta.from_attachment(b"\xff garbage") == FrameMeta()
    assert FrameMeta.from_attachment(None) == FrameMeta()
    c = DropCounter()
    for s in (0, 1, 4, 5):
        c.update(FrameMeta(seq=s, src="a"))
    c.update(FrameMeta(seq=0, src="b"))  # another source: its own sequence
    c.update(FrameMeta(seq=0, src="a"))  # publisher restarted
    c.update(FrameMeta(seq=2, src="a"))
    c.update(FrameMeta())
    assert (c.dropped, c.restarts, c.unsequenced) == (3, 1, 1)


def test_frames_roundtrip_with_sequence_attachment():
    listen, connect = session_pair()
    with open_session(listen) as a, open_session(connect) as b:
        sub = FrameSubscriber(a, "robot/camera/image", queue_size=8)
        pub = FramePublisher(b, "robot/camera/image", congestion="block")
        assert pub.wait_for_subscriber(10)
        images = sample_images(4, size=(64, 48))
        sent = [encode_frame(img, "png") for img in images]
        for i, (payload, enc) in enumerate(sent):
            assert pub.put(payload, enc, stamp_ns=1000 + i) == i
        got = []
        while len(got) < len(sent):
            frame = sub.receive(5.0)
            assert frame is not None, f"only {len(got)} frames arrived"
            got.append(frame)
        assert [f.meta.seq for f in got] == [0, 1, 2, 3]
        assert [f.stamp_ns for f in got] == [1000, 1001, 1002, 1003]
        assert all(f.encoding == "image/png" and f.payload == s[0] for f, s in zip(got, sent))
        assert sub.drops.dropped == 0 and sub.received == 4
        assert sub.receive(0.05) is None
        pub.close()
        sub.close()


def test_ring_channel_keeps_newest_and_counts_drops():
    listen, connect = session_pair()
    n, ring = 40, 3
    with open_session(listen) as a, open_session(connect) as b:
        sub = FrameSubscriber(a, "cam/image", queue_size=ring)
        last_seen = threading.Event()

        def watch(sample: zenoh.Sample) -> None:
            if FrameMeta.from_attachment(sample.attachment.to_bytes()).seq == n - 1:
                last_seen.set()

        watcher = a.declare_subscriber("cam/image", watch)
        pub = FramePublisher(b, "cam/image", congestion="block")
        assert pub.wait_for_subscriber(10)
        payload, enc = encode_frame(sample_images(1, size=(64, 48))[0], "jpeg")
        for _ in range(n):
            pub.put(payload, enc)
        assert last_seen.wait(10), "the last frame never arrived"
        got = []
        while not got or got[-1].meta.seq != n - 1:
            frame = sub.receive(5.0)
            assert frame is not None
            got.append(frame)
        assert len(got) <= ring + 1  # the newest frames won
        # gaps are counted from the first frame received on
        assert got[0].meta.seq > 0
        assert sub.drops.dropped == n - got[0].meta.seq - len(got)
        watcher.undeclare()
        pub.close()
        sub.close()


def test_receive_returns_on_stop_event():
    listen, _ = session_pair()
    with open_session(listen) as a:
        sub = FrameSubscriber(a, "nobody/publishes/here")
        stop = threading.Event()
        stop.set()
        assert sub.receive(30.0, stop) is None  # returns at once, not after 30 s
        with pytest.raises(ConfigError):
            FrameSubscriber(a, "x", queue_size=0)
        sub.close()


def test_config_file_mode_is_kept_unless_given(tmp_path):
    """A --config file saying `mode: "client"` is honoured; an explicit mode still wins."""
    import json

    from aefabmap_runtime.adapters.zenoh_transport import SessionConfig, build_zenoh_config

    cfg = tmp_path / "zenoh.json5"
    cfg.write_text('{ mode: "client", connect: { endpoints: ["tcp/127.0.0.1:7447"] } }')
    assert json.loads(build_zenoh_config(SessionConfig(config_file=str(cfg))).get_json("mode")) == "client"
    assert json.loads(build_zenoh_config(SessionConfig(config_file=str(cfg), mode="peer")).get_json("mode")) == "peer"
    assert json.loads(build_zenoh_config(SessionConfig()).get_json("mode")) == "peer"


def test_a_config_file_never_falls_back_to_listening_everywhere_or_multicast_scouting(tmp_path):
    """An empty --config ({}) used to listen on every interface and join multicast scouting."""
    import json

    from aefabmap_runtime.errors import ConfigError
    from aefabmap_runtime.adapters.zenoh_transport import SessionConfig, build_zenoh_config

    empty = tmp_path / "empty.json5"
    empty.write_text("{}")
    with pytest.raises(ConfigError, match="chooses no listen or connect endpoints"):
        build_zenoh_config(SessionConfig(config_file=str(empty)))
    conf = build_zenoh_config(SessionConfig(config_file=str(empty), connect=("tcp/127.0.0.1:7447",)))
    assert json.loads(conf.get_json("listen/endpoints")) == []
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    conf = build_zenoh_config(SessionConfig(config_file=str(empty), listen=("tcp/127.0.0.1:0",)))
    assert json.loads(conf.get_json("listen/endpoints")) == ["tcp/127.0.0.1:0"]
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    chosen = tmp_path / "chosen.json5"
    chosen.write_text('{ listen: { endpoints: ["tcp/127.0.0.1:0"] }, scouting: { multicast: { enabled: true } } }')
    with pytest.raises(ConfigError, match="would expose the node .*joins multicast scouting.*--allow-exposure"):
        build_zenoh_config(SessionConfig(config_file=str(chosen)))
    conf = build_zenoh_config(SessionConfig(config_file=str(chosen), allow_exposure=True))  # what a file says, it gets
    assert json.loads(conf.get_json("listen/endpoints")) == ["tcp/127.0.0.1:0"]
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is True


@pytest.mark.parametrize("listen, exposed", [
    ("tcp/127.0.0.1:0", False), ("tcp/[::1]:0", False), ("tcp/localhost:0", False), ("udp/127.0.0.2:0", False),
    ("unixsock-stream//tmp/aefabmap-test.sock", False), ("tcp/0.0.0.0:0", True), ("tcp/[::]:0", True),
    ("tcp/192.168.1.20:7447", True), ("tcp/robot.local:7447", True), ("tls/0.0.0.0:0", True),
    ("quic/10.0.0.1:7447", True),
])
def test_exposure_of_listen_endpoints(tmp_path, listen, exposed):
    """Attacker's view: whatever another host can reach without a certificate needs --allow-exposure, from a
    config file or from --listen alike."""
    import json

    from aefabmap_runtime.errors import ConfigError
    from aefabmap_runtime.adapters.zenoh_transport import SessionConfig, build_zenoh_config, session_exposure

    conf_file = tmp_path / "z.json5"
    conf_file.write_text(json.dumps({"listen": {"endpoints": [listen]}}))
    for sc in (SessionConfig(config_file=str(conf_file)), SessionConfig(listen=(listen,))):
        assert bool(session_exposure(sc)) == exposed
        if exposed:
            with pytest.raises(ConfigError, match=f"would expose the node \\(listens on {re.escape(listen)}"):
                build_zenoh_config(sc)
        build_zenoh_config(dataclasses.replace(sc, allow_exposure=True))


def test_mutual_tls_listeners_are_not_exposure(tmp_path):
    """A TLS/QUIC listener whose peers must show a certificate of the configured CA is authenticated; TLS
    without client certificates, or a plain TCP endpoint beside it, is not."""
    import json

    from aefabmap_runtime.adapters.zenoh_transport import SessionConfig, session_exposure

    def exposure_of(doc):
        path = tmp_path / "z.json5"
        path.write_text(json.dumps(doc))
        return session_exposure(SessionConfig(config_file=str(path)))

    tls = {"root_ca_certificate": "ca.pem", "listen_certificate": "node.pem", "listen_private_key": "node.key"}
    listen = {"endpoints": ["tls/0.0.0.0:7447"]}
    assert exposure_of({"listen": listen, "transport": {"link": {"tls": {**tls, "enable_mtls": True}}}}) == []
    assert exposure_of({"listen": listen, "transport": {"link": {"tls": tls}}}) != []
    both = {"endpoints": ["tls/0.0.0.0:7447", "tcp/0.0.0.0:7448"]}
    assert exposure_of({"listen": both, "transport": {"link": {"tls": {**tls, "enable_mtls": True}}}}) == [
        "listens on tcp/0.0.0.0:7448 without client authentication"]
