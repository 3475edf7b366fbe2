"""Robots of a fleet over real Zenoh sessions through a router on loopback
(runtime/aefabmap_runtime/adapters/fleet.py): places offered, fetched on demand and verified; late joiners;
robots that leave; hostile peers."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
import zenoh

from aefabmap_runtime.adapters.bundle_reader import load_detector
from aefabmap_runtime.adapters.fleet import FleetNode
from aefabmap_runtime.adapters.state_dir import bundle_id
from aefabmap_runtime.adapters.zenoh_transport import SessionConfig, open_session
from aefabmap_runtime.core.detector import DetectorConfig
from aefabmap_runtime.core.fleet.fleet_map import FleetConfig
from aefabmap_runtime.core.fleet.fleet_wire import PlaceSummary, fleet_key
from aefabmap_runtime.tools.node_process import free_tcp_port

pytestmark = pytest.mark.timeout(120)


@pytest.fixture(scope="module")
def route():
    from aefabmap_runtime.tools.synthetic_route import generate_loop_sequence

    images, _ = generate_loop_sequence(10, seed=3, size=(640, 480))
    return images


@pytest.fixture
def hub():
    """A Zenoh router on a loopback port; yields its endpoint."""
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    router = open_session(SessionConfig(listen=(ep,), mode="router"))
    yield ep
    router.close()


def _peer(hub: str) -> zenoh.Session:
    """A peer that reaches the router and listens on loopback, as a robot's node does: the router
    tells the peers of each other and they connect directly."""
    return open_session(SessionConfig(connect=(hub,), listen=(f"tcp/127.0.0.1:{free_tcp_port()}",), mode="peer"))


def _robot(hub: str, robot: str, **kw) -> tuple[zenoh.Session, FleetNode]:
    from aefabmap.cli.demo import default_bundle

    session = _peer(hub)
    det = load_detector(default_bundle(), DetectorConfig(exclude=1))
    return session, FleetNode(session, det, FleetConfig(name="test", robot=robot, **kw))


def _until(condition, timeout_s: float = 10.0) -> bool:
    """Wait (bounded) for a condition that Zenoh's threads make true."""
    deadline, pause = time.monotonic() + timeout_s, threading.Event()
    while not condition():
        if time.monotonic() > deadline:
            return False
        pause.wait(0.02)
    return True


def _feed(node: FleetNode, images) -> list:
    return [node.detector.process(im, 0) for im in images]


def test_a_robot_verifies_a_view_of_anothers_place_fetching_its_keypoints(hub, route):
    sa, a = _robot(hub, "a")
    sb, b = _robot(hub, "b")
    try:
        # b's token reaching a means b's subscription (declared before it) reached the router too
        assert _until(lambda: a.robots_alive() == ["b"])
        _feed(a, route[:6])
        offered = a.fleet_stats().places_served
        assert offered == 5  # frames 0-4 entered a's map (exclude 1)
        assert _until(lambda: (b.detector.process(np.zeros((480, 640), np.uint8), 0), b.map.n_places)[1] == offered)
        r = b.detector.process(route[3], 0)
        assert r.verified and r.verified_robot == "a" and abs(r.verified_frame - 3) <= 1
        assert r.verified_place is None and r.loop
        s = b.fleet_stats().robots["a"]
        assert s.fetches >= 1 and s.fetch_failures == 0 and s.loops == 1 and s.bytes_in > 0 and s.alive
        assert a.fleet_stats().keypoint_replies >= 1 and a.fleet_stats().bytes_out > 0
        to_b = a.fleet_stats().robots["b"]  # a holds none of b's places, but counts what it sent b
        assert to_b.keypoint_replies == a.fleet_stats().keypoint_replies and 0 < to_b.bytes_out < a.fleet_stats().bytes_out
        # b's own map never holds a's places: a frame of b's own route verifies to b (robot null)
        r2 = b.detector.process(route[3], 0)  # again: still a's place (b stored its own copy only after exclude)
        assert r2.verified
    finally:
        a.close(), b.close(), sa.close(), sb.close()


def test_a_late_joiner_gets_every_place_with_one_query_and_a_leaver_is_noticed(hub, route):
    sa, a = _robot(hub, "a", fetch_timeout_ms=200)
    _feed(a, route[:6])
    sc, c = _robot(hub, "c", fetch_timeout_ms=200)
    try:
        assert _until(lambda: c.robots_alive() == ["a"])
        assert c.join(timeout_s=5) == 5
        c.detector.process(np.zeros((480, 640), np.uint8), 0)
        assert c.map.n_places == 5
        a.close()
        sa.close()  # robot a leaves: its liveliness token goes
        assert _until(lambda: c.fleet_stats().robots["a"].alive is False)
        r = c.detector.process(route[3], 0)  # a's places stay usable, but their keypoints cannot be fetched
        assert not r.verified and r.verified_robot is None
        s = c.fleet_stats().robots["a"]
        assert s.places == 5 and s.fetches >= 1 and s.fetch_failures == s.fetches
    finally:
        c.close(), sc.close()


def test_hostile_peers_are_counted_and_cannot_crash_or_overfill_a_node(hub, route):
    sb, b = _robot(hub, "b", max_places=4, fetch_timeout_ms=300)
    evil = _peer(hub)
    token = evil.liveliness().declare_token(fleet_key("test", "x", "alive", str(evil.zid())))
    assert _until(lambda: b.robots_alive() == ["x"])
    ident = bytes.fromhex(bundle_id(b.detector.manifest))
    try:
        garbage = [b"", b"AEFS", b"\xff" * 64, PlaceSummary("x", bytes(32), 1, 0, np.array([1, 2])).encode(),
                   PlaceSummary("y", ident, 1, 0, np.array([3, 2])).encode()]
        for i, data in enumerate(garbage):
            evil.put(fleet_key("test", "x", "place", str(i)), data)
        # a summary that names another robot than its key
        evil.put(fleet_key("test", "x", "place", "9"), PlaceSummary("z", ident, 9, 0, np.array([1, 2])).encode())
        # many valid places from one peer: the node keeps no more than its cap
        for frame in range(40):
            evil.put(fleet_key("test", "x", "place", str(100 + frame)),
                     PlaceSummary("x", ident, 100 + frame, 0, np.arange(frame, frame + 50)).encode())

        def refused():
            st = b.fleet_stats()
            return sum(st.refused_elsewhere.values()) + sum(sum(r.refused.values()) for r in st.robots.values())

        assert _until(lambda: (b.detector.process(np.zeros((480, 640), np.uint8), 0), refused() >= 6 and
                               b.fleet_stats().robots.get("x") is not None and
                               b.fleet_stats().robots["x"].summaries >= 40)[1])
        assert b.map.n_places <= 4
        # the peer answers keypoint queries with garbage: the fetch is refused and counted
        replies = evil.declare_queryable(fleet_key("test", "x", "keypoints", "*"),
                                         lambda q: q.reply(str(q.key_expr), b"AEFK" + b"\0" * 40))
        r = b.detector.process(route[3], 0)
        assert not r.verified
        st = b.fleet_stats().robots["x"]
        assert st.fetches >= 1 and st.fetch_failures == st.fetches and st.refused.get("malformed", 0) >= 1
        replies.undeclare()
        token.undeclare()
    finally:
        b.close(), sb.close(), evil.close()


def _restarted_a(hub, route, read_only: bool = False) -> tuple[zenoh.Session, FleetNode]:
    """Robot a maps route 0-5 (places 0-4) and leaves; a new node loads its map (read-only:
    localizing) and rejoins as a."""
    from aefabmap.cli.demo import default_bundle

    sa, a = _robot(hub, "a")
    _feed(a, route[:6])
    state = a.detector.state().resolve()
    a.close()
    sa.close()
    det = load_detector(default_bundle(), DetectorConfig(exclude=1))
    det.load_state(state)
    det.map.read_only = read_only
    session = _peer(hub)
    return session, FleetNode(session, det, FleetConfig(name="test", robot="a"))


def test_a_restarted_node_serves_the_places_of_its_loaded_map(hub, route):
    s2, again = _restarted_a(hub, route)
    sc, c = _robot(hub, "c")
    try:
        assert _until(lambda: c.robots_alive() == ["a"])
        assert again.fleet_stats().places_served == 5
        assert c.join(timeout_s=5) == 5
        r = c.detector.process(route[3], 0)
        assert r.verified and r.verified_robot == "a" and abs(r.verified_frame - 3) <= 1
    finally:
        again.close(), s2.close(), c.close(), sc.close()


def test_places_stored_while_a_robot_was_unreachable_arrive_when_it_is_back(hub, route):
    """a leaves the fleet (its token goes) and goes on mapping; when it is back, b asks it for the
    places after the latest one b holds, and gets exactly those."""
    sa, a = _robot(hub, "a")
    sb, b = _robot(hub, "b")
    blank = np.zeros((480, 640), np.uint8)
    try:
        assert _until(lambda: a.robots_alive() == ["b"] and b.robots_alive() == ["a"])
        _feed(a, route[:4])  # frames 0-2 stored (exclude 1)
        assert _until(lambda: (b.detector.process(blank, 0), b.map.n_places)[1] == 3)
        detector = a.detector
        a.close()
        sa.close()
        assert _until(lambda: b.robots_alive() == [])
        received = b.fleet_stats().robots["a"].summaries
        for im in route[4:8]:  # mapped while unreachable: nothing reaches b
            detector.process(im, 0)
        sa = _peer(hub)
        a = FleetNode(sa, detector, FleetConfig(name="test", robot="a"))  # back, serving its whole map
        assert a.fleet_stats().places_served == 7
        assert _until(lambda: b.robots_alive() == ["a"])
        assert _until(lambda: (b.detector.process(blank, 0), b.map.n_places)[1] == 7)
        held = sorted(b.map.robots["a"].place_of)
        assert held == list(range(7)) and b.map.last_frame("a") == 6
        assert b.fleet_stats().robots["a"].summaries - received == 4  # only the missed ones were sent again
        assert a.fleet_stats().bytes_out < 7 * len(a._served[0][0])
    finally:
        a.close(), b.close(), sa.close(), sb.close()


def test_a_summaries_query_with_a_bad_after_parameter_gets_no_reply(hub, route):
    sa, a = _robot(hub, "a")
    peer = _peer(hub)
    try:
        _feed(a, route[:4])
        key = fleet_key("test", "a", "summaries")

        def ask(selector: str, timeout: float = 2.0) -> list:  # every reply: they share one key
            return list(peer.get(selector, timeout=timeout, consolidation=zenoh.ConsolidationMode.NONE))

        assert _until(lambda: len(ask(key)) == 3)
        assert len(ask(f"{key}?after=1")) == 1
        for bad in ("x", "-5", "1e3", "9" * 30, ""):
            assert ask(f"{key}?after={bad}", 0.5) == []
    finally:
        a.close(), sa.close(), peer.close()


def _image_log(path, images):
    """An MCAP log of `images` (PNG) by a run whose places enter the map after one frame (exclude 1)."""
    import cv2

    from aefabmap_runtime.core.run_config import RUN_CONFIG_KEY
    from aefabmap_runtime.adapters.mcap_log import McapLogWriter
    from aefabmap_runtime.core.run_config import RunConfig

    run = RunConfig(detector=DetectorConfig(exclude=1)).to_dict()
    with McapLogWriter(path, run_config={RUN_CONFIG_KEY: run}) as log:
        for i, img in enumerate(images):
            png = cv2.imencode(".png", img)[1].tobytes()
            log.write_image(png, "image/png", 1_700_000_000_000_000_000 + i * 100_000_000, sequence=i)
    return path


def test_replay_fleet_offers_the_map_it_builds_from_a_log_until_stopped(hub, route, tmp_path):
    from aefabmap.cli import replay as cli_replay
    from aefabmap.cli.demo import default_bundle
    from tests.conftest import cli_args

    log_path = _image_log(tmp_path / "a.mcap", route[:6])
    args = cli_args("replay", log_path, "--model", default_bundle(), "--fleet", "test", "--robot", "a",
                    "--connect", hub, "--listen", f"tcp/127.0.0.1:{free_tcp_port()}")
    stop, codes = threading.Event(), []
    replayer = threading.Thread(target=lambda: codes.append(cli_replay.main(args, stop)), daemon=True)
    sb, b = _robot(hub, "b")
    blank = np.zeros((480, 640), np.uint8)
    try:
        replayer.start()
        # the replay's places reach b live or by catch-up; they stay offered after the replay ends
        assert _until(lambda: (b.detector.process(blank, 0), b.map.n_places)[1] == 5, timeout_s=60)
        r = b.detector.process(route[3], 0)
        assert r.verified and r.verified_robot == "a" and abs(r.verified_frame - 3) <= 1
        assert replayer.is_alive()  # serving until stopped
    finally:
        stop.set()
        replayer.join(timeout=30)
        b.close(), sb.close()
    assert codes == [0]


@pytest.mark.parametrize("extra, words", [
    (["--fleet", "test"], "go together"),
    (["--fleet", "test", "--robot", "a", "--check"], "--check"),
    (["--connect", "tcp/127.0.0.1:7"], "are for --fleet"),
])
def test_replay_fleet_option_errors_are_one_line(tmp_path, route, extra, words, caplog):
    from aefabmap.cli import replay as cli_replay
    from aefabmap.cli.demo import default_bundle
    from tests.conftest import cli_args

    log_path = _image_log(tmp_path / "a.mcap", route[:2])
    assert cli_replay.main(cli_args("replay", log_path, "--model", default_bundle(), *extra)) == 2
    errors = [r.getMessage() for r in caplog.records if r.levelname == "ERROR"]
    assert len(errors) == 1 and words in errors[0]


def test_a_restarted_robots_place_refused_before_its_epoch_was_confirmed_is_asked_for_again(hub, route):
    """The restarted robot's first place arrives before its new epoch is confirmed (refused, not
    believed by itself), its second after: the catch-up that follows the restart asks for all its
    places, not for those after the second, so the first is not lost."""
    sa, a = _robot(hub, "a")
    sb, b = _robot(hub, "b")
    blank = np.zeros((480, 640), np.uint8)
    try:
        assert _until(lambda: b.robots_alive() == ["a"])
        _feed(a, route[:4])  # frames 0-2 stored
        assert _until(lambda: (b.detector.process(blank, 0), b.map.n_places)[1] == 3)
        a.close(), sa.close()
        sa, a = _robot(hub, "a")  # no --state: a new epoch
        fresh = a.detector
        assert _until(lambda: b.robots_alive() == ["a"])
        _feed(a, route[4:6])  # its frame 0 stored and published

        def refused() -> int:
            return b.map.robots["a"].stats.refused.get("unconfirmed_epoch", 0)

        assert _until(lambda: (b.detector.process(blank, 0), refused())[1] >= 1)  # and a's epoch asked
        _feed(a, route[6:7])  # its frame 1 stored and published
        assert _until(lambda: len(b._inbox) >= 1 and len(b._epochs) >= 1)  # both wait for b's next frame
        b.detector.process(blank, 0)  # the epoch confirmed, frame 1 taken, then the catch-up asked
        assert b.map.epoch("a") == fresh.map_epoch
        assert _until(lambda: (b.detector.process(blank, 0), sorted(b.map.robots["a"].place_of))[1] == [0, 1])
    finally:
        a.close(), sa.close(), b.close(), sb.close()


def test_askers_named_by_keypoint_queries_are_checked_and_bounded(hub, route):
    sa, a = _robot(hub, "a", max_robots=3)
    peer = _peer(hub)
    try:
        _feed(a, route[:3])  # frame 0 stored
        key = fleet_key("test", "a", "keypoints", "0")
        assert _until(lambda: len(list(peer.get(key, timeout=2))) == 1)
        for name in ["*", "a$b", "x" * 40, *[f"r{i}" for i in range(10)]]:
            assert len(list(peer.get(f"{key}?robot={name}", timeout=2))) == 1  # answered, counted or not
        robots = a.fleet_stats().robots
        assert set(robots) == {"r0", "r1", "r2"} and all(r.keypoint_replies == 1 for r in robots.values())
        assert a.fleet_stats().keypoint_replies == 14
    finally:
        a.close(), sa.close(), peer.close()


def test_a_robot_restarted_without_its_map_is_forgotten_and_read_again(hub, route):
    """Frame numbers of a robot restarted without its state mean other places: the others drop
    what they held of it (keypoints cached included) and take its new places."""
    sa, a = _robot(hub, "a")
    sb, b = _robot(hub, "b")
    blank = np.zeros((480, 640), np.uint8)
    try:
        assert _until(lambda: b.robots_alive() == ["a"])
        _feed(a, route[:6])  # frames 0-4 stored: route 0-4
        assert _until(lambda: (b.detector.process(blank, 0), b.map.n_places)[1] == 5)
        assert b.detector.process(route[3], 0).verified_frame in (2, 3, 4)  # fetched and cached
        old_epoch = b.map.epoch("a")
        a.close(), sa.close()
        sa, a = _robot(hub, "a")  # no --state
        fresh = a.detector
        _feed(a, route[6:9])  # its frames 0-1 are route 6-7 now
        assert _until(lambda: (b.detector.process(blank, 0), b.map.epoch("a"))[1] == fresh.map_epoch)
        assert _until(lambda: (b.detector.process(blank, 0), sorted(b.map.robots["a"].place_of))[1] == [0, 1])
        assert fresh.map_epoch != old_epoch and b.fleet_stats().robots["a"].map_restarts == 1
        r = b.detector.process(route[3], 0)  # route 3 is no place of a's new map: never a loop to a's frame 3
        assert r.verified_robot != "a" or r.verified_frame not in (2, 3, 4)
    finally:
        a.close(), b.close(), sa.close(), sb.close()


def test_nodes_that_only_connect_to_the_router_join_as_clients_and_exchange_places(hub, route, tmp_path):
    """Two Zenoh peers that only connect to a router exchange nothing; `fleet_session` makes such
    nodes clients, which the router serves (here: replay --fleet and a robot, neither listening)."""
    from aefabmap.cli import replay as cli_replay
    from aefabmap.cli.demo import default_bundle
    from aefabmap_runtime.adapters.node_session import fleet_session
    from tests.conftest import cli_args

    fleet = FleetConfig(name="test", robot="b")
    only_connect = SessionConfig(connect=(hub,))
    assert fleet_session(only_connect, fleet).mode == "client"
    for kept in (SessionConfig(connect=(hub,), listen=("tcp/127.0.0.1:7",)), SessionConfig(connect=(hub,), mode="peer"),
                 SessionConfig(listen=("tcp/127.0.0.1:7",))):
        assert fleet_session(kept, fleet) == kept  # a listen endpoint, a chosen mode, or no router
    assert fleet_session(only_connect, None) == only_connect
    log_path = _image_log(tmp_path / "a.mcap", route[:6])
    args = cli_args("replay", log_path, "--model", default_bundle(), "--fleet", "test", "--robot", "a",
                    "--connect", hub)
    stop, codes = threading.Event(), []
    replayer = threading.Thread(target=lambda: codes.append(cli_replay.main(args, stop)), daemon=True)
    sb = open_session(fleet_session(only_connect, fleet))
    b = FleetNode(sb, load_detector(default_bundle(), DetectorConfig(exclude=1)), fleet)
    blank = np.zeros((480, 640), np.uint8)
    try:
        replayer.start()
        assert _until(lambda: (b.detector.process(blank, 0), b.map.n_places)[1] == 5, timeout_s=60)
        r = b.detector.process(route[3], 0)
        assert r.verified and r.verified_robot == "a"
    finally:
        stop.set()
        replayer.join(timeout=30)
        b.close(), sb.close()
    assert codes == [0]


def test_places_stored_during_a_network_partition_arrive_once_it_heals(route):
    """a and b are clients of two routers; b's router goes down (a partition: a maps on, b hears
    nothing) and comes back: b sees a's token again and gets exactly the places it missed."""
    e1, e2 = f"tcp/127.0.0.1:{free_tcp_port()}", f"tcp/127.0.0.1:{free_tcp_port()}"
    r1 = open_session(SessionConfig(listen=(e1,), mode="router"))
    r2 = open_session(SessionConfig(listen=(e2,), connect=(e1,), mode="router"))
    sa = open_session(SessionConfig(connect=(e1,), mode="client"))
    sb = open_session(SessionConfig(connect=(e2,), mode="client"))
    from aefabmap.cli.demo import default_bundle

    a = FleetNode(sa, load_detector(default_bundle(), DetectorConfig(exclude=1)), FleetConfig(name="test", robot="a"))
    b = FleetNode(sb, load_detector(default_bundle(), DetectorConfig(exclude=1)), FleetConfig(name="test", robot="b"))
    blank = np.zeros((480, 640), np.uint8)
    try:
        assert _until(lambda: b.robots_alive() == ["a"])
        _feed(a, route[:4])  # frames 0-2 stored
        assert _until(lambda: (b.detector.process(blank, 0), b.map.n_places)[1] == 3)
        r2.close()  # the partition
        assert _until(lambda: b.robots_alive() == [])
        _feed(a, route[4:8])  # frames 3-6 stored: b hears nothing of them
        assert a.fleet_stats().places_served == 7 and b.map.n_places == 3
        r2 = open_session(SessionConfig(listen=(e2,), connect=(e1,), mode="router"))  # healed
        assert _until(lambda: b.robots_alive() == ["a"], 60)
        assert _until(lambda: (b.detector.process(blank, 0), b.map.n_places)[1] == 7)
        assert sorted(b.map.robots["a"].place_of) == list(range(7))
    finally:
        a.close(), b.close(), sa.close(), sb.close(), r2.close(), r1.close()


def _holding_a_calibrated_place(hub, tmp_path):
    """Robot b in the fleet (a detector with --camera) holding robot a's place 7, whose keypoints it
    fetched before, and b's query of the same scene (tests/runtime/core/decide/test_candidates.py):
    (b's session, b, the scene, the query's words, the query)."""
    from aefabmap_runtime.core.verify.verification import VerificationConfig
    from tests.runtime.core.decide.test_candidates import CAMERA, calibrated_scene
    from tests.runtime.core.verify.test_verification import _detector

    scene = calibrated_scene()
    det = _detector(tmp_path, verification=VerificationConfig(camera=CAMERA, min_inliers_h=1000))
    words = np.arange(scene.n) % det.bundle.vocabulary_size
    sb = _peer(hub)
    b = FleetNode(sb, det, FleetConfig(name="test", robot="b"))
    b.map.add(PlaceSummary("a", b.identity, 7, 0, np.unique(words), epoch=5))
    place = scene.frame(scene.points)
    b.map._cache[("a", 7)] = det.map.store.pack(place.keypoints, words, place.descriptors, (480, 640))
    return sb, b, scene, words, scene.frame(scene.query)


def test_a_calibrated_loop_to_another_robots_place_carries_the_relative_pose(hub, tmp_path):
    """Two views of one 3-D point cloud: a's place, b's query; with --camera the remote loop
    carries b's camera pose in a's place frame."""
    sb, b, scene, words, query = _holding_a_calibrated_place(hub, tmp_path)
    try:
        result = b.detector.process_words(words, features=query)  # b's own map is empty: the core asks a's places
        assert result.verified and result.verified_robot == "a" and result.verified_frame == 7
        assert result.geometry_model == "E" and result.relative_rotation is not None
        R = np.asarray(result.relative_rotation)  # as for the own places (test_candidates.py)
        assert np.degrees(np.arccos(np.clip((np.trace(R.T @ scene.rotation) - 1) / 2, -1, 1))) < 0.5
        assert np.allclose(result.relative_translation, scene.centre / np.linalg.norm(scene.centre), atol=0.01)
    finally:
        b.close(), sb.close()


def test_the_core_builds_a_remote_loops_result_once_and_the_node_never_edits_it(hub, tmp_path, monkeypatch):
    """The frame loop's processor is the detector alone: a fleet node processes nothing and stands
    in for nothing; a loop to another robot's place is in the FrameResult the core builds, and
    nothing edits that result afterwards."""
    from aefabmap_runtime.core import detector as core_detector

    assert not any(hasattr(FleetNode, name) for name in ("process", "process_words", "__getattr__", "manifest"))
    built, build = [], core_detector.FrameResult

    def record(**fields):
        result = build(**fields)
        built.append((result, result.to_dict()))
        return result

    monkeypatch.setattr(core_detector, "FrameResult", record)
    sb, b, _, words, query = _holding_a_calibrated_place(hub, tmp_path)
    try:
        result = b.detector.process_words(words, features=query)
        (first, as_built), = built
        assert first is result and as_built["loop"] and as_built["verified_robot"] == "a"
        assert as_built["verified_place"] is None and as_built["temporal_ok"] is None
        assert result.to_dict() == as_built and "remote" in result.timings_ms
        assert b.fleet_stats().robots["a"].loops == 1
    finally:
        b.close(), sb.close()
    alone = b.detector.process_words(words, features=query)  # b left the fleet: no other robot is asked
    assert not alone.loop and alone.verified_robot is None and "remote" not in alone.timings_ms


def test_a_node_offers_exactly_the_places_its_map_holds(hub, route):
    """Insertions, evictions (a cap) and a loaded map reach the node as map events: what it
    offers is always what the own map holds."""
    from aefabmap.cli.demo import default_bundle

    sa = _peer(hub)
    det = load_detector(default_bundle(), DetectorConfig(exclude=1, max_places=3))
    a = FleetNode(sa, det, FleetConfig(name="test", robot="a"))
    try:
        for im in route[:7]:
            det.process(im, 0)
            assert sorted(a._served) == sorted(frame for _, frame in det.map.places())
        assert a.fleet_stats().places_served == 3 and a.fleet_stats().summaries_out == 6
        other = load_detector(default_bundle(), DetectorConfig(exclude=1, max_places=3))
        for im in route[7:10]:
            other.process(im, 0)
        det.load_state(other.state().resolve())
        assert sorted(a._served) == sorted(frame for _, frame in det.map.places()) == [0, 1]
        vocabulary = det.map.vocabulary_size
        assert {PlaceSummary.decode(summary, a.identity, vocabulary).epoch for summary, _ in a._served.values()} == {
            other.map_epoch}  # offered under the loaded map's numbering
    finally:
        a.close(), sa.close()


def test_a_peer_declaring_many_robots_cannot_grow_the_node_without_bound(hub):
    sb, b = _robot(hub, "b", max_robots=4)
    evil = _peer(hub)
    tokens = [evil.liveliness().declare_token(fleet_key("test", f"r{i}", "alive", str(evil.zid()))) for i in range(30)]
    tokens.append(evil.liveliness().declare_token(fleet_key("test", "x" * 40, "alive", str(evil.zid()))))  # not a robot id
    try:
        assert _until(lambda: len(b.robots_alive()) == 4)
        assert len(b._alive) == 4 and len(b._returned) <= 4
        b.detector.process(np.zeros((480, 640), np.uint8), 0)  # catch-up queries to the robots it holds: no crash
        followed = b.robots_alive()
        tokens.pop(int(followed[0][1:])).undeclare()  # one of them leaves: a newcomer takes its room
        newcomer = evil.liveliness().declare_token(fleet_key("test", "late", "alive", str(evil.zid())))
        tokens.append(newcomer)
        assert _until(lambda: "late" in b.robots_alive()) and len(b._alive) == 4
    finally:
        for t in tokens:
            t.undeclare()
        b.close(), sb.close(), evil.close()


def test_a_localizing_node_offers_its_read_only_map_and_keeps_it_unchanged(hub, route):
    """--localize with --fleet: the frozen map's places are offered as a loaded map's are; the
    node's own frames enter nothing, so it offers no new place."""
    s2, frozen = _restarted_a(hub, route, read_only=True)
    sc, c = _robot(hub, "c")
    try:
        assert _until(lambda: c.robots_alive() == ["a"])
        assert c.join(timeout_s=5) == 5
        _feed(frozen, route[6:9])  # a localizes on: nothing enters its map, nothing new is offered
        assert frozen.fleet_stats().places_served == 5 and frozen.fleet_stats().summaries_out == 0
        r = c.detector.process(route[3], 0)
        assert r.verified and r.verified_robot == "a" and abs(r.verified_frame - 3) <= 1
    finally:
        frozen.close(), s2.close(), c.close(), sc.close()
