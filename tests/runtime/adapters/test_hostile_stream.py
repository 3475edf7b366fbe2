"""A hostile peer on the Zenoh stream: attachments are untrusted, out-of-range times never
reach the MCAP writer, and the node keeps running with a readable log."""

from __future__ import annotations

import json
import os
import time

import pytest
import zenoh

from aefabmap_runtime.errors import LogError
from aefabmap_runtime.adapters.frames import encode_frame
from aefabmap_runtime.adapters.mcap_log import McapLogReader, McapLogWriter
from aefabmap_runtime.adapters.zenoh_transport import (
    MAX_ATTACHMENT_BYTES,
    DropCounter,
    FrameMeta,
    FramePublisher,
    build_zenoh_config,
    cli_session_config,
    open_session,
)
from aefabmap_runtime.tools.node_process import free_tcp_port

from .stream_fakes import (
    KEY,
    RESULTS,
    STATS,
    FakeDetector,
    JsonCollector,
    NodeThread,
    sample_images,
    session_pair,
)

pytestmark = pytest.mark.timeout(90)

#: Attachments a hostile or broken publisher may send; each must be refused (counted).
HOSTILE_ATTACHMENTS = [
    b'{"seq": 0, "stamp_ns": -5, "src": "x"}',
    json.dumps({"seq": 1, "stamp_ns": 2**64, "src": "x"}).encode(),
    json.dumps({"seq": 2, "stamp_ns": 10**400, "src": "x"}).encode(),
    b'{"seq": 3, "stamp_ns": 1e30, "src": "x"}',
    b'{"seq": 4, "stamp_ns": NaN, "src": "x"}',
    b'{"seq": 5, "stamp_ns": "1700000000000000000", "src": "x"}',
    b'{"seq": true, "src": "x"}',
    b'{"seq": -1, "src": "x"}',
    json.dumps({"seq": 2**70, "src": "x"}).encode(),
    b'{"seq": 6, "src": ["not", "a", "string"]}',
    json.dumps({"seq": 7, "src": "s" * 500}).encode(),
    json.dumps({"seq": 8, "src": "s" * (MAX_ATTACHMENT_BYTES + 1)}).encode(),
    b"\xff\xfe not utf-8",
    b"not json at all",
    b"[1, 2, 3]",
    b"42",
    b"[" * 1000,  # nesting deeper than the JSON parser's recursion limit
    b"1" * 5000,  # an integer too long to convert
]


@pytest.mark.parametrize("attachment", HOSTILE_ATTACHMENTS, ids=range(len(HOSTILE_ATTACHMENTS)))
def test_hostile_attachment_is_refused_and_reported(attachment):
    meta = FrameMeta.from_attachment(attachment)
    assert meta.problem
    assert meta.stamp_ns is None or 0 <= meta.stamp_ns < 2**63
    assert meta.seq is None or 0 <= meta.seq < 2**63
    assert isinstance(meta.src, str) and len(meta.src) <= 64


def test_good_and_absent_attachments_have_no_problem():
    good = FrameMeta(seq=3, stamp_ns=42, src="cam")
    assert FrameMeta.from_attachment(good.to_attachment()) == good
    assert not FrameMeta.from_attachment(good.to_attachment()).problem
    assert not FrameMeta.from_attachment(None).problem
    assert not FrameMeta.from_attachment(FrameMeta().to_attachment()).problem  # all null: unsequenced
    # the fields that are fine are kept when another one is refused
    mixed = FrameMeta.from_attachment(b'{"seq": 9, "stamp_ns": -5, "src": "cam"}')
    assert (mixed.seq, mixed.stamp_ns, mixed.src) == (9, None, "cam") and "stamp_ns" in mixed.problem


def test_drop_counter_tracks_a_bounded_number_of_sources():
    c = DropCounter()
    for i in range(10 * DropCounter.MAX_SOURCES):
        c.update(FrameMeta(seq=0, src=f"src{i}"))
    assert len(c._last) == DropCounter.MAX_SOURCES
    assert c.dropped == 0 and c.restarts == 0


def test_a_sequence_jump_no_publisher_could_make_is_not_counted_as_drops():
    """One attachment with seq 2^63-1 after 0 must not set `dropped` to 9.2e18 for the rest of
    the run: it is counted as a jump (like a restart) and counting goes on from it."""
    c = DropCounter()
    for seq in (0, 1, 2**63 - 1, 2**63, 2**63 + 3):
        c.update(FrameMeta(seq=seq, src="cam"))
    assert c.dropped == 2 and c.restarts == 1
    c.update(FrameMeta(seq=2**63 + 3 + DropCounter.MAX_GAP, src="cam"))  # the largest gap still counted
    assert c.dropped == 2 + DropCounter.MAX_GAP - 1


@pytest.mark.parametrize("stamp", [-5, 2**64, 2**70])
def test_mcap_writer_refuses_out_of_range_times_and_the_log_stays_readable(tmp_path, stamp):
    path = tmp_path / "t.mcap"
    payload, enc = encode_frame(sample_images(1, size=(64, 48))[0], "jpeg")
    with McapLogWriter(path) as log:
        log.write_image(payload, enc, 1_000, sequence=0)
        with pytest.raises(LogError, match="time"):
            log.write_image(payload, enc, stamp, sequence=1)
        with pytest.raises(LogError, match="time"):
            log.write_result({"sequence": 1, "stamp_ns": stamp})
        with pytest.raises(LogError, match="time"):
            log.write_stats({"frames": 1}, log_time_ns=stamp)
        log.write_image(payload, enc, 2_000, sequence=2)
    reader = McapLogReader(path)
    frames = list(reader.frames())
    assert not reader.status.truncated
    assert [f.stamp_ns for f in frames] == [1_000, 2_000]


def test_node_survives_hostile_attachments_and_falls_back_to_receive_time(tmp_path):
    listen, connect = session_pair()
    log_path = tmp_path / "hostile.mcap"
    payload, enc = encode_frame(sample_images(1, size=(64, 48))[0], "jpeg")
    n_bad = len(HOSTILE_ATTACHMENTS)
    with NodeThread(detector=FakeDetector(threshold=-1.0), session_config=listen, key=KEY, mcap_path=log_path,
                    queue_size=64, stats_period_s=0.2) as node:
        with open_session(connect) as s:
            results = JsonCollector(s, RESULTS)
            stats = JsonCollector(s, STATS)
            probe = FramePublisher(s, KEY, congestion="block")
            assert probe.wait_for_subscriber(10)
            raw = s.declare_publisher(KEY, congestion_control=zenoh.CongestionControl.BLOCK)
            t_before = time.time_ns()
            for att in HOSTILE_ATTACHMENTS:
                raw.put(payload, encoding=zenoh.Encoding(enc), attachment=att)
            probe.put(payload, enc, stamp_ns=1_700_000_000_000_000_000)  # one good frame last
            docs = results.wait_for(lambda d: d["sequence"] == n_bad, timeout_s=20)
            t_after = time.time_ns()
            stat = stats.wait_for(lambda d: d["bad"].get("bad_attachment") == n_bad, timeout_s=20)[-1]
            assert node.thread.is_alive()
            raw.undeclare()
            probe.close()
            results.close()
            stats.close()
        summary = node.finish()
    assert [d["sequence"] for d in docs] == list(range(n_bad + 1))
    assert all(t_before <= d["stamp_ns"] <= t_after for d in docs[:n_bad])  # receive time
    assert docs[-1]["stamp_ns"] == 1_700_000_000_000_000_000
    assert stat["frames_processed"] == n_bad + 1
    assert summary.bad["bad_attachment"] == n_bad and summary.frames_processed == n_bad + 1
    reader = McapLogReader(log_path)
    frames = list(reader.frames())
    assert not reader.status.truncated and len(frames) == n_bad + 1
    assert [f.stamp_ns for f in frames] == [d["stamp_ns"] for d in docs]


# --------------------------------------------------------------------------- network exposure


def _bound_sockets() -> set[tuple[str, str]]:
    """(protocol, local address) of the TCP listening and UDP sockets this process holds
    (Linux /proc; addresses as hex ``IP:PORT``, IPv4 loopback = ``0100007F``)."""
    inodes = set()
    for fd in os.listdir("/proc/self/fd"):
        try:
            target = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            continue
        if target.startswith("socket:["):
            inodes.add(target[8:-1])
    found = set()
    for proto in ("tcp", "tcp6", "udp", "udp6"):
        with open(f"/proc/net/{proto}") as f:
            for line in f.readlines()[1:]:
                cols = line.split()
                local, state, inode = cols[1], cols[3], cols[9]
                if inode in inodes and (proto.startswith("udp") or state == "0A"):
                    found.add((proto, local))
    return found


def _is_loopback(proto: str, local: str) -> bool:
    ip = local.rsplit(":", 1)[0]
    if proto.endswith("6"):
        return ip in ("00000000000000000000000001000000", "0000000000000000FFFF00000100007F")
    return ip.endswith("7F") and len(ip) == 8  # 127.x.x.x, little-endian hex


@pytest.mark.skipif(not os.path.isdir("/proc/self/fd"), reason="needs Linux /proc")
@pytest.mark.parametrize("role", ["listen", "connect"])
def test_cli_default_session_is_loopback_only_without_multicast(role):
    port = free_tcp_port()
    sc = cli_session_config(role, connect=(), listen=(), config_file=None, default_port=port)
    assert (sc.listen if role == "listen" else sc.connect) == (f"tcp/127.0.0.1:{port}",)
    conf = build_zenoh_config(sc)
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    if role == "connect":
        assert json.loads(conf.get_json("listen/endpoints")) == []  # a publisher listens nowhere
        return
    before = _bound_sockets()
    with open_session(sc):
        opened = _bound_sockets() - before
    assert opened, "the node should listen on loopback"
    assert all(_is_loopback(p, a) for p, a in opened), opened


@pytest.mark.skipif(not os.path.isdir("/proc/self/fd"), reason="needs Linux /proc")
def test_explicit_connect_adds_no_listener():
    listen, connect = session_pair()
    with open_session(listen):
        before = _bound_sockets()
        sc = cli_session_config("listen", connect=connect.connect, listen=(), config_file=None)
        assert sc.listen == () and sc.connect == connect.connect
        with open_session(sc):
            assert _bound_sockets() - before == set()


def test_explicit_options_and_config_file_are_kept(tmp_path):
    sc = cli_session_config("listen", connect=(), listen=("tcp/0.0.0.0:7447",), config_file=None)
    assert sc.listen == ("tcp/0.0.0.0:7447",) and sc.connect == ()
    conf_file = tmp_path / "z.json5"
    conf_file.write_text("{ listen: { endpoints: ['tcp/127.0.0.1:0'] }, scouting: { multicast: { enabled: true } } }")
    sc = cli_session_config("listen", connect=(), listen=(), config_file=str(conf_file), allow_exposure=True)
    assert sc.listen == () and sc.config_file == str(conf_file)
    conf = build_zenoh_config(sc)  # multicast scouting: exposure, accepted here
    assert json.loads(conf.get_json("listen/endpoints")) == ["tcp/127.0.0.1:0"]  # the file decides
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is True
