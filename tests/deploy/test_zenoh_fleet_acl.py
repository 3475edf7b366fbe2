"""The shipped fleet configs with mutual TLS and access control (deploy/zenoh-fleet-router.json5,
deploy/zenoh-fleet-robot.json5), real sessions on loopback: robots a and b exchange places and
verify loops; a participant the CA signed without a robot role, and robot c lying in a's name or
as a made-up robot, get no forged place, reply, token or restart through: 0 forged loops."""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

from aefabmap_runtime.adapters.zenoh_transport import SessionConfig, open_session, session_authenticated
from aefabmap_runtime.core.fleet.fleet_wire import PlaceSummary, encode_keypoints, fleet_key
from aefabmap_runtime.tools.node_process import free_tcp_port
from tests.runtime.adapters.test_fleet import _until

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "scripts"))
from fleet_tls import make_certificates, robot_config, router_config  # noqa: E402

pytestmark = [pytest.mark.skipif(shutil.which("openssl") is None, reason="needs the openssl command"),
              pytest.mark.timeout(240)]

BLANK = np.zeros((480, 640), np.uint8)


def _settle(node, condition, timeout_s: float = 15.0) -> bool:
    return _until(lambda: (node.detector.process(BLANK, 0), condition())[1], timeout_s)


@pytest.fixture
def fleet_tls(tmp_path):
    """Certificates (fleet router, robots a, b, c, a stranger named 'forger'), the router running the
    shipped config, and a function opening a robot's session from the shipped robot config."""
    d = tmp_path / "tls"
    d.mkdir()
    make_certificates(d, ("fleet-router", "a", "b", "c", "forger"))
    port = free_tcp_port()
    router = open_session(SessionConfig(config_file=str(router_config(d, port))))
    sessions = []

    def session(name: str):
        sc = SessionConfig(config_file=str(robot_config(d, name, port, f"tcp/127.0.0.1:{free_tcp_port()}")))
        assert session_authenticated(sc)
        s = open_session(sc)
        sessions.append(s)
        return s

    yield session
    for s in sessions:
        s.close()
    router.close()


def _node(session, robot: str, **kw):
    from aefabmap.cli.demo import default_bundle
    from aefabmap_runtime.adapters.bundle_reader import load_detector
    from aefabmap_runtime.adapters.fleet import FleetNode
    from aefabmap_runtime.core.detector import DetectorConfig
    from aefabmap_runtime.core.fleet.fleet_map import FleetConfig

    det = load_detector(default_bundle(), DetectorConfig(exclude=1))
    return FleetNode(session, det, FleetConfig(name="test", robot=robot, **kw))


def _forge(session, victim_identity: bytes, views, epoch: int) -> list:
    """Every forgery the attack suite tried, from `session`: a made-up robot 'm' offering b's
    upcoming views (token, summaries, keypoint answers); a's name taken (token, a place a never
    stored, keypoint answers racing a's own, a new epoch at frame 2^62). Returns the handles."""
    handles = []
    zid = str(session.zid())
    kps = {frame: k for frame, (_, k) in enumerate(views)}

    def answer(query):
        frame = int(str(query.key_expr).rpartition("/")[2])
        place = kps.get(frame % len(views))
        query.reply(str(query.key_expr), encode_keypoints(victim_identity, frame, place, epoch))

    for robot in ("m", "a"):
        handles.append(session.liveliness().declare_token(fleet_key("test", robot, "alive", zid)))
        handles.append(session.declare_queryable(fleet_key("test", robot, "keypoints", "*"), answer))
    for frame, (words, _) in enumerate(views):
        session.put(fleet_key("test", "m", "place", str(frame)),
                    PlaceSummary("m", victim_identity, frame, 0, words, epoch).encode())
        session.put(fleet_key("test", "a", "place", str(99 + frame)),
                    PlaceSummary("a", victim_identity, 99 + frame, 0, words, epoch).encode())
    session.put(fleet_key("test", "a", "place", str(2**62)),
                PlaceSummary("a", victim_identity, 2**62, 0, views[0][0], epoch + 1).encode())
    return handles


def test_no_forged_loop_place_or_restart_gets_through_the_shipped_tls_and_acl(fleet_tls, route_images):
    from tests.runtime.adapters.test_fleet_hostile import _stored_views

    route = route_images
    a = _node(fleet_tls("a"), "a")
    b = _node(fleet_tls("b"), "b", fetch_timeout_ms=1000)
    forgers = [fleet_tls("forger"), fleet_tls("c")]  # a stranger the CA signed, and a robot lying
    handles = []
    try:
        assert _until(lambda: b.robots_alive() == ["a"])
        for im in route[:6]:  # frames 0-4 stored
            a.detector.process(im, 0)
        assert _settle(b, lambda: b.map.n_places == 5)
        epoch = b.map.epoch("a")
        views = _stored_views(route[6:10])  # what b sees next
        for forger in forgers:
            handles += _forge(forger, b.identity, views, epoch)
        a.detector.process(route[6], 0)  # a's next place, sent after the forgeries: once it is in, they had their chance
        assert _settle(b, lambda: b.map.n_places == 6)
        results = [b.detector.process(im, 0) for im in route[6:10]]
        assert not any(r.verified_robot == "m" for r in results)
        assert not any(r.verified_robot == "a" and r.verified_frame >= 99 for r in results)
        assert b.robots_alive() == ["a"] and sorted(b.map.robots) == ["a"]
        assert sorted(b.map.robots["a"].place_of) == [0, 1, 2, 3, 4, 5] and b.map.epoch("a") == epoch
        held = b.fleet_stats()
        assert held.robots["a"].map_restarts == 0 and "not_from_owner" not in held.refused_elsewhere
        # the fleet itself works with TLS on: a true revisit of a's place verifies to it
        r = b.detector.process(route[3], 0)
        assert r.verified and r.verified_robot == "a" and abs(r.verified_frame - 3) <= 1
    finally:
        for h in handles:
            h.undeclare()
        a.close(), b.close()


@pytest.fixture(scope="module")
def route_images():
    from aefabmap_runtime.tools.synthetic_route import generate_loop_sequence

    images, _ = generate_loop_sequence(10, seed=3, size=(640, 480))
    return images


def test_without_tls_the_same_forgeries_do_get_a_loop(route_images):
    """The control: on a router without access control the made-up robot's places verify (the
    node warns at start that such a fleet's peers are not authenticated)."""
    from tests.runtime.adapters.test_fleet import _peer
    from tests.runtime.adapters.test_fleet_hostile import _stored_views

    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    router = open_session(SessionConfig(listen=(ep,), mode="router"))
    sb, forger = _peer(ep), _peer(ep)
    b = _node(sb, "b", fetch_timeout_ms=1000)
    handles = []
    try:
        views = _stored_views(route_images[6:10])
        handles = _forge(forger, b.identity, views, 0)
        assert _settle(b, lambda: "m" in b.map.robots and b.map.n_places >= len(views))
        results = [b.detector.process(im, 0) for im in route_images[6:10]]
        assert any(r.verified_robot == "m" for r in results)
    finally:
        for h in handles:
            h.undeclare()
        b.close(), sb.close(), forger.close(), router.close()


def test_a_fleet_node_says_once_at_start_when_its_peers_are_not_authenticated(tmp_path, caplog):
    from aefabmap_runtime.adapters.node_session import Endpoints, node_session
    from aefabmap_runtime.core.fleet.fleet_map import FleetConfig

    d = tmp_path / "tls"
    d.mkdir()
    make_certificates(d, ("b",))
    fleet = FleetConfig(name="lab", robot="b")
    caplog.set_level("WARNING")
    node_session(Endpoints(connect=("tcp/127.0.0.1:7447",)), fleet=fleet)
    warned = [r.getMessage() for r in caplog.records if "not authenticated" in r.getMessage()]
    assert len(warned) == 1 and "fleet lab" in warned[0] and "zenoh-fleet-router.json5" in warned[0]
    caplog.clear()
    node_session(Endpoints(config_file=str(robot_config(d, "b", 7448, "tcp/127.0.0.1:7447"))), fleet=fleet)
    node_session(Endpoints(connect=("tcp/127.0.0.1:7447",)), fleet=None)  # not in a fleet: nothing to say
    assert not [r for r in caplog.records if "not authenticated" in r.getMessage()]
    assert not session_authenticated(SessionConfig(listen=("tcp/127.0.0.1:7447",)))
