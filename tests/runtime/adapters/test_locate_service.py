"""The "where am I?" queryable of a running node (runtime/aefabmap_runtime/adapters/locate_service.py),
as a real `aefabmap run --state M --localize` process: images of the second lap are located in
the first lap's map, nothing is inserted; oversized, malformed and flooding queries are refused
with a reason while the node goes on answering."""

from __future__ import annotations

import subprocess
import threading

import numpy as np
import pytest

from aefabmap_runtime.adapters.frames import encode_frame
from aefabmap_runtime.adapters.zenoh_transport import FramePublisher, locate_key_for, open_session
from aefabmap_runtime.core.records.messages import LocateAnswer
from aefabmap_runtime.tools.localize_eval import state_digest
from aefabmap_runtime.tools.synthetic_route import generate_loop_sequence

from .stream_fakes import CLI, KEY, RESULTS, session_pair

N, HALF = 40, 20
LOCATE = locate_key_for(RESULTS)


@pytest.fixture(scope="module")
def node(tmp_path_factory):
    """A localize node over the map of the first lap (built in process), its session, the images."""
    from aefabmap.cli.demo import default_bundle
    from aefabmap_runtime.adapters.bundle_reader import load_detector
    from aefabmap_runtime.adapters.state_dir import MapStateDir, bundle_id
    from aefabmap_runtime.core.detector import DetectorConfig

    tmp = tmp_path_factory.mktemp("locate")
    images, gt = generate_loop_sequence(N, seed=3, size=(640, 480))
    det = load_detector(default_bundle(), DetectorConfig(exclude=1))
    for im in images[:HALF]:
        det.process(im, 0)
    with MapStateDir(tmp / "state", bundle_id(det.manifest)) as d:
        d.save(det.state())
    before = state_digest(tmp / "state")
    listen, connect = session_pair()
    proc = subprocess.Popen(CLI + ["run", "--model", str(default_bundle()), "--key", KEY, "--listen", listen.listen[0],
                                   "--mcap", str(tmp / "run.mcap"), "--state", str(tmp / "state"), "--localize",
                                   "--exclude", "1"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    session = open_session(connect)
    try:
        probe = FramePublisher(session, KEY)
        assert probe.wait_for_subscriber(60), "the node never subscribed"
        probe.close()
        yield session, images, gt, det.place_frames()
    finally:
        session.close()
        proc.terminate()
        _, err = proc.communicate(timeout=60)
        assert proc.returncode == 0, err[-2000:]
        assert state_digest(tmp / "state") == before


def _ask(session, payload: bytes, encoding: str | None = "image/png", timeout: float = 30.0):
    """(LocateAnswer or None, error text or None) of one query."""
    kw = {"payload": payload}
    if encoding is not None:
        kw["encoding"] = encoding
    for reply in session.get(LOCATE, timeout=timeout, **kw):
        if reply.ok is not None:
            return LocateAnswer.from_json(reply.ok.payload.to_bytes()), None
        return None, reply.err.payload.to_string()
    return None, None


def _ask_paced(session, payload: bytes, encoding: str | None = "image/png"):
    """`_ask`, waiting for the rate's next token when told busy (a client that keeps the rate)."""
    pause = threading.Event()
    for _ in range(50):
        answer, err = _ask(session, payload, encoding)
        if err is None or not err.startswith("busy"):
            return answer, err
        pause.wait(0.25)
    return None, "busy for ever"


@pytest.mark.timeout(240)
def test_images_of_the_second_lap_are_located_in_the_first_laps_map(node):
    session, images, gt, _ = node
    located = []
    for i in range(HALF, N):
        png, _ = encode_frame(images[i], "png")
        answer, err = _ask_paced(session, png)
        assert err is None and answer is not None
        if answer.verified:
            located.append((i, answer.frame))
            assert answer.frame < HALF and answer.inliers > 0 and answer.nfa < -4 and answer.places > 0
    assert located
    jpeg, _ = encode_frame(images[HALF + 1], "jpeg")
    answer, err = _ask_paced(session, jpeg, encoding=None)  # no encoding: told by its magic
    assert err is None and answer is not None


@pytest.mark.timeout(240)
def test_hostile_queries_are_refused_with_a_reason_and_the_node_goes_on(node):
    session, images, _, _ = node
    _, err = _ask(session, b"\0" * (9 << 20))
    assert err is not None and err.startswith("too_large")
    _, err = _ask_paced(session, b"\x89PNG\r\n\x1a\n" + b"\xff" * 100)
    assert err is not None and err.startswith("bad_image")
    _, err = _ask_paced(session, b"", encoding="image/png")
    assert err is not None and err.startswith("bad_image")
    _, err = _ask_paced(session, np.zeros(64, np.uint8).tobytes(), encoding="mono8;4000000x4000000")
    assert err is not None and err.startswith("bad_image")
    # A flood: 60 queries at once from 6 threads; the rate and the queue bound them.
    png, _ = encode_frame(images[HALF + 2], "png")
    errors, answers, lock = [], [], threading.Lock()

    def flood():
        for _ in range(10):
            a, e = _ask(session, png)
            with lock:
                (answers if a is not None else errors).append(e)

    threads = [threading.Thread(target=flood) for _ in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(120)
    assert len(answers) + len(errors) == 60 and len(errors) >= 40  # a few get through as the bucket refills
    assert all(e.startswith("busy") for e in errors)
    a, e = _ask_paced(session, png)  # and afterwards the node answers as before
    assert a is not None and e is None
