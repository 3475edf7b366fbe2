"""Frames in flight across worker threads (runtime/aefabmap_runtime/adapters/frame_pipeline.py): the
results of one thread in every field but the timings, in order, with bad frames counted as before
and a bounded number of frames in flight."""

from __future__ import annotations

import threading

import cv2
import numpy as np
import pytest

from aefabmap_runtime.adapters.bundle_reader import load_detector
from aefabmap_runtime.adapters.frame_loop import FrameLoop
from aefabmap_runtime.adapters.frame_pipeline import FramePipeline, pipelined
from aefabmap_runtime.adapters.frames import encode_frame
from aefabmap_runtime.core.detector import DetectorConfig
from aefabmap_runtime.core.run_config import MAX_WORKERS, RunConfig
from aefabmap_runtime.errors import ConfigError
from aefabmap_runtime.tools.synthetic_route import generate_loop_sequence

from .stream_fakes import FakeDetector


@pytest.fixture(scope="module")
def route_files(tmp_path_factory):
    """A synthetic route with revisits as PNG files, a broken file and a too-small image among them."""
    folder = tmp_path_factory.mktemp("route")
    images, _ = generate_loop_sequence(36, seed=3, size=(320, 240))
    paths = []
    for i, image in enumerate(images):
        paths.append(folder / f"{i:04d}.png")
        cv2.imwrite(str(paths[-1]), image)
    (folder / "0007.png").write_bytes(b"not a png")  # corrupt: counted, the run goes on
    cv2.imwrite(str(folder / "0011.png"), np.zeros((4, 4), np.uint8))  # decodes; the detector refuses 4x4
    return paths


def _default_detector():
    from aefabmap.cli.demo import default_bundle

    return load_detector(default_bundle(), DetectorConfig(exclude=3))


def _run(paths, workers: int):
    loop = FrameLoop(_default_detector())
    outcomes = [(i, out) for i, out in pipelined(loop, ((i, p, i) for i, p in enumerate(paths)), workers)]
    return loop, outcomes


def _without_timings(result) -> dict:
    doc = result.to_dict()
    doc.pop("timings_ms")
    return doc


@pytest.mark.parametrize("workers", [2, 3])
def test_results_are_one_threads_in_every_field_but_the_timings(route_files, workers):
    one, sequential = _run(route_files, 1)
    many, parallel = _run(route_files, workers)
    assert [i for i, _ in parallel] == list(range(len(route_files)))  # every frame, in order
    assert [o.bad_reason for _, o in parallel] == [o.bad_reason for _, o in sequential]
    mine = [_without_timings(o.result) for _, o in parallel if o.result is not None]
    theirs = [_without_timings(o.result) for _, o in sequential if o.result is not None]
    assert mine == theirs and len(mine) == len(route_files) - 2
    assert any(r["verified"] for r in mine)  # the route revisits: loops were decided, not only new places
    assert (many.frames_in, many.processed, many.loops) == (one.frames_in, one.processed, one.loops)
    assert {k: v for k, v in many.bad.counts.items() if v} == {"corrupt": 1, "rejected": 1}


def test_frames_in_flight_stay_within_the_depth(route_files):
    """The frames prepared ahead never exceed the depth, however fast the workers are."""
    loop = FrameLoop(_default_detector())
    prepared, lock = [], threading.Lock()
    inner = loop.detector.prepare

    def counting(gray):
        with lock:
            prepared.append(threading.current_thread().name)
        return inner(gray)

    loop.detector.prepare = counting
    taken = 0
    with FramePipeline(loop, workers=3, depth=4) as pipe:
        for i, path in enumerate(route_files[:20]):
            pipe.put_file(i, path, i)
            assert pipe.pending <= 4
            while pipe.full:
                pipe.take()
                taken += 1
                with lock:
                    assert len(prepared) <= taken + 4
        while pipe.pending:
            pipe.take()
    assert loop.frames_in == 20
    assert any(name.startswith("aefabmap-frame") for name in prepared)


def test_one_worker_decides_each_frame_as_frame_loop_step_does(route_files):
    """workers=1 is the loop of before: each frame decoded and processed at its turn, no thread."""
    loop = FrameLoop(FakeDetector())
    seen = []
    with FramePipeline(loop, workers=1, before=seen.append) as pipe:
        assert pipe.depth == 1
        for i, path in enumerate(route_files[:5]):
            pipe.put_file(i, path, i)
            assert pipe.full
            i_taken, out = pipe.take()
            assert i_taken == i and (out.result is not None or out.bad_reason)
    assert seen == list(range(5)) and loop.frames_in == 5


def test_a_stand_in_without_prepare_needs_one_worker():
    with pytest.raises(ConfigError, match="workers"):
        FramePipeline(FrameLoop(FakeDetector()), workers=2)
    with pytest.raises(ConfigError, match="no frame"):
        FramePipeline(FrameLoop(FakeDetector())).take()


def test_payloads_and_transport_refusals_keep_their_order():
    from aefabmap_runtime.adapters.frame_loop import PreparedInput
    from aefabmap_runtime.adapters.frames import FrameError

    images, _ = generate_loop_sequence(6, seed=1, size=(320, 240))
    loop = FrameLoop(_default_detector())
    with FramePipeline(loop, workers=2) as pipe:
        for i, image in enumerate(images):
            if i == 2:
                error = FrameError("not_image", "broken CDR")
                pipe.put_prepared(i, PreparedInput(error=error, reason=error.reason), i)
            else:
                payload, encoding = encode_frame(image, "png")
                pipe.put_payload(i, payload, encoding, i)
        got = [pipe.take() for _ in range(len(images))]
    assert [i for i, _ in got] == list(range(len(images)))
    assert got[2][1].bad_reason == "not_image"
    assert [o.result.sequence for i, o in got if i != 2] == list(range(5))


@pytest.mark.parametrize("bad", [0, -1, MAX_WORKERS + 1, True, 2.0, "2"])
def test_worker_counts_out_of_range_are_refused(bad):
    with pytest.raises(ConfigError, match="workers"):
        RunConfig(workers=bad)
    with pytest.raises(ConfigError, match="workers"):
        RunConfig.from_dict({**RunConfig().to_dict(), "workers": bad})


def test_frame_threads_hold_python_s_lock_longer_while_open_and_give_it_back():
    """With frame threads, a waiting thread asks for Python's lock after SWITCH_INTERVAL_S (never
    sooner than the process had it); closing the pipeline restores the process's interval, as it
    does OpenCV's thread count."""
    import sys

    from aefabmap_runtime.adapters.frame_pipeline import SWITCH_INTERVAL_S

    before, threads = sys.getswitchinterval(), cv2.getNumThreads()
    with FramePipeline(FrameLoop(_default_detector()), workers=2):
        assert sys.getswitchinterval() == max(before, SWITCH_INTERVAL_S) and cv2.getNumThreads() == 1
    assert sys.getswitchinterval() == before and cv2.getNumThreads() == threads
    with FramePipeline(FrameLoop(_default_detector()), workers=1):
        assert sys.getswitchinterval() == before
