"""Hostile peers of a fleet over real Zenoh sessions through a router on loopback, without TLS
(runtime/aefabmap_runtime/adapters/fleet.py): what a node believes only from a robot's own
session, and the bounds a stranger cannot push past. With the shipped TLS + access-control
config a stranger cannot even send these (tests/deploy/test_zenoh_fleet_acl.py)."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest

from aefabmap_runtime.core.fleet.fleet_wire import PlaceSummary, encode_keypoints, fleet_key
from aefabmap_runtime.core.map.map_events import MapListener
from tests.runtime.adapters.test_fleet import _feed, _peer, _robot, _until, hub, route  # noqa: F401 - fixtures

pytestmark = pytest.mark.timeout(180)

BLANK = np.zeros((480, 640), np.uint8)


class _Inserted(MapListener):
    def __init__(self) -> None:
        self.places = []

    def place_inserted(self, place, frame, words, keypoints) -> None:
        self.places.append((frame, words, keypoints))


def _stored_views(images):
    """(words, keypoints) of each image as a detector stores it: what a forger shows as its places."""
    from aefabmap.cli.demo import default_bundle
    from aefabmap_runtime.adapters.bundle_reader import load_detector
    from aefabmap_runtime.core.detector import DetectorConfig

    det = load_detector(default_bundle(), DetectorConfig(exclude=1))
    rec = _Inserted()
    det.add_listener(rec)
    for im in [*images, BLANK]:
        det.process(im, 0)
    return [(np.unique(words[words >= 0]), kps) for _, words, kps in rec.places]


def _settle(node, condition, timeout_s: float = 10.0) -> bool:
    """Feed blank frames (each reads what arrived) until condition holds."""
    return _until(lambda: (node.detector.process(BLANK, 0), condition())[1], timeout_s)


def _rss_mb() -> float:
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmRSS:")) / 1024


def test_a_forged_epoch_or_keypoint_reply_from_another_session_changes_nothing(hub, route):
    """The attack: a's summary re-sent with a new epoch and frame 2^62 (which made b forget a's
    places and then ask only for frames after 2^62), and a queryable on a's keypoint key that
    answers every frame with the keypoints of b's query (which won the race and redirected loops)."""
    sa, a = _robot(hub, "a")
    sb, b = _robot(hub, "b", fetch_timeout_ms=1000)
    evil = _peer(hub)
    try:
        assert _until(lambda: b.robots_alive() == ["a"])
        _feed(a, route[:6])  # frames 0-4 stored
        assert _settle(b, lambda: b.map.n_places == 5)
        epoch = b.map.epoch("a")
        summary = PlaceSummary.decode(a._served[2][0], b.identity, b.detector.map.vocabulary_size)
        forged = replace(summary, frame=2**62, epoch=epoch + 1)
        evil.put(fleet_key("test", "a", "place", str(2**62)), forged.encode())
        assert _settle(b, lambda: b.map.robots["a"].stats.refused.get("unconfirmed_epoch") == 1)
        assert _settle(b, lambda: not b._epoch_asked)  # a's own session was asked, and answered
        b.detector.process(BLANK, 0)
        assert b.map.epoch("a") == epoch and b.map.n_places == 5 and b.map.last_frame("a") == 4
        assert b.fleet_stats().robots["a"].map_restarts == 0

        # A place a never stored, offered in a's name with a's epoch (a publication carries no sender
        # Zenoh vouches for: TLS + ACL stops it), and a racing queryable that answers for it.
        (words, query_kps), = _stored_views([route[8]])
        evil.put(fleet_key("test", "a", "place", "99"), PlaceSummary("a", b.identity, 99, 0, words, epoch).encode())
        assert _settle(b, lambda: 99 in b.map.robots["a"].place_of)
        forged_reply = lambda q: q.reply(str(q.key_expr), encode_keypoints(  # noqa: E731
            b.identity, int(str(q.key_expr).rpartition("/")[2]), query_kps, epoch))
        racer = evil.declare_queryable(fleet_key("test", "a", "keypoints", "*"), forged_reply)
        r = b.detector.process(route[8], 0)
        assert not (r.verified and r.verified_robot == "a"), b.fleet_stats()
        r = b.detector.process(route[3], 0)  # a's own reply still counts: the true revisit
        assert r.verified and r.verified_robot == "a" and abs(r.verified_frame - 3) <= 1, b.fleet_stats().robots["a"]
        assert b.fleet_stats().refused_elsewhere.get("not_from_owner", 0) >= 1
        racer.undeclare()
    finally:
        a.close(), b.close(), sa.close(), sb.close(), evil.close()


# The attacker: the router the node connects to (a router is its own process in a deployment,
# and its buffers are not the node's), publishing 300 summaries of 1 MiB of junk once the node's
# token shows it is subscribed.
_JUNK_ROUTER = """
import zenoh
conf = zenoh.Config()
conf.insert_json5("mode", '"router"')
conf.insert_json5("listen/endpoints", '["%s"]')
conf.insert_json5("scouting/multicast/enabled", "false")
s = zenoh.open(conf)
while not list(s.liveliness().get("aefabmap/fleet/test/b/alive/*", timeout=1)):
    pass
junk = bytes(range(256)) * 4096  # 1 MiB
for i in range(300):
    s.put("aefabmap/fleet/test/x/place/%%d" %% i, junk, congestion_control=zenoh.CongestionControl.BLOCK)
print("sent", flush=True)
input()  # stay up until the test has measured
"""


def test_megabytes_of_junk_summaries_do_not_grow_a_node():
    from aefabmap.cli.demo import default_bundle
    from aefabmap_runtime.adapters.bundle_reader import load_detector
    from aefabmap_runtime.adapters.fleet import FleetNode
    from aefabmap_runtime.adapters.zenoh_transport import SessionConfig, open_session
    from aefabmap_runtime.core.detector import DetectorConfig
    from aefabmap_runtime.core.fleet.fleet_map import FleetConfig
    from aefabmap_runtime.tools.node_process import free_tcp_port

    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    attacker = subprocess.Popen([sys.executable, "-c", _JUNK_ROUTER % ep], stdin=subprocess.PIPE,
                                stdout=subprocess.PIPE, text=True)
    try:
        det = load_detector(default_bundle(), DetectorConfig(exclude=1))
        det.process(BLANK, 0)
        sb = None
        assert _until(lambda: attacker.poll() is None and _connect(ep) is not None, 30)
        sb = open_session(SessionConfig(connect=(ep,), mode="client"))
        before = _rss_mb()
        b = FleetNode(sb, det, FleetConfig(name="test", robot="b"))
        assert attacker.stdout.readline().strip() == "sent"
        assert _until(lambda: b._drops >= 300, 30)  # every 1 MiB summary refused unread, none queued
        grown = _rss_mb() - before
        b.detector.process(BLANK, 0)
        assert b.fleet_stats().refused_elsewhere["too_large_or_inbox_full"] >= 300 and not b._inbox
        print(f"RSS growth after 300 x 1 MiB of junk summaries: {grown:.1f} MB")
        assert grown <= 64, f"RSS grew by {grown:.0f} MB"
        b.close()
    finally:
        if sb is not None:
            sb.close()
        attacker.kill()
        attacker.communicate(timeout=30)


def _connect(ep: str):
    """Whether a TCP connection to the endpoint's port succeeds now (the attacker's router is up)."""
    import socket

    host, port = ep.partition("/")[2].rsplit(":", 1)
    try:
        with socket.create_connection((host, int(port)), timeout=1):
            return True
    except OSError:
        return None


def test_summaries_under_made_up_robot_ids_do_not_lock_out_a_real_robot(hub, route):
    sb, b = _robot(hub, "b")
    evil = _peer(hub)
    try:
        views = _stored_views(route[:2])
        for i in range(16):
            evil.put(fleet_key("test", f"fake{i}", "place", "0"),
                     PlaceSummary(f"fake{i}", b.identity, 0, 0, views[0][0]).encode())
        assert _settle(b, lambda: b.fleet_stats().refused_elsewhere.get("not_alive", 0) == 16)
        assert b.map.robots == {}
        sa, a = _robot(hub, "a")
        try:
            _feed(a, route[:6])
            assert _settle(b, lambda: b.map.n_places == 5)
            assert list(b.map.robots) == ["a"]
        finally:
            a.close(), sa.close()
    finally:
        b.close(), sb.close(), evil.close()


def test_twelve_peers_that_hold_every_query_cost_one_deadline_per_frame(hub, route):
    """Twelve robots whose keypoint queryables never answer: a frame that asks all of them (two
    places each) waits for them at once, one deadline in all, not one per robot in series."""
    deadline_ms = 400
    sb, b = _robot(hub, "b", fetch_timeout_ms=deadline_ms)
    slow = _peer(hub)
    held = []  # the queries the slow robots hold open, never answering
    handles = []
    try:
        views = _stored_views(route[:4])
        robots = [f"slow{i}" for i in range(12)]
        for robot in robots:
            handles.append(slow.liveliness().declare_token(fleet_key("test", robot, "alive", str(slow.zid()))))
            handles.append(slow.declare_queryable(fleet_key("test", robot, "keypoints", "*"), held.append))
        assert _until(lambda: b.robots_alive() == sorted(robots))
        for robot in robots:
            for frame, (words, _) in enumerate(views):
                slow.put(fleet_key("test", robot, "place", str(frame)), PlaceSummary(robot, b.identity, frame, 0,
                                                                                     words).encode())
        assert _settle(b, lambda: b.map.n_places == 12 * len(views))
        for im in route[1:4]:
            r = b.detector.process(im, 0)
            print(f"12 slow robots, deadline {deadline_ms} ms: remote stage {r.timings_ms['remote']:.0f} ms")
            assert not r.verified
            assert r.timings_ms["remote"] < 2 * deadline_ms, r.timings_ms  # serially: 24 x the deadline
        stats = b.fleet_stats().robots
        assert all(stats[robot].fetches >= 2 and stats[robot].fetch_failures == stats[robot].fetches for robot in robots)
    finally:
        held.clear()
        for h in handles:
            h.undeclare()
        b.close(), sb.close(), slow.close()
