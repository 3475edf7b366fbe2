"""Frames in flight across worker threads: the next frames are read, decoded and extracted while
the current one is decided.

A frame's preparation (decode, features, words: `FrameLoop.prepare_*`) needs no map, so it can run
on any thread; its decision (rank, verify, decide, insert: `FrameLoop.finish`) needs the map as
the frames before left it, so it runs on the caller's thread, in the order the frames came. The
results are those of one thread in every field but the timings. OpenCV, onnxruntime and the
compiled kernels release Python's lock while they work, so threads share the cores.

`workers` counts the threads that work on frames, the caller's included: 1 runs everything on the
caller's thread as before; N adds N - 1 threads. While the caller waits for the oldest frame it
prepares a later one itself. At most `depth` frames are in flight (bounded memory). With N > 1,
OpenCV's own thread pool is held at one thread while the pipeline is open: the cores go to frames,
not to OpenCV's threads waiting on one another; and a thread waiting for Python's lock asks its
holder to hand it over after SWITCH_INTERVAL_S rather than Python's default: every return from
OpenCV, onnxruntime or a kernel already hands the lock over, and forced hand-overs between the two
frame threads cost CPU without adding work done (docs/results.md, "Frames in flight").
"""

from __future__ import annotations

import sys
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, Generic, TypeVar

import cv2

from aefabmap_runtime.errors import ConfigError
from aefabmap_runtime.adapters.frame_loop import FrameLoop, FrameOutcome, PreparedInput
from aefabmap_runtime.core.run_config import check_workers

T = TypeVar("T")

#: Seconds a thread waits for Python's lock before it asks the holder for it, while frame threads
#: run (module doc); Python's default is a quarter of it.
SWITCH_INTERVAL_S = 0.02


class _Job(Generic[T]):
    """One frame in flight: its context (what the caller gets back), its stamp and its preparation."""

    __slots__ = ("context", "stamp_ns", "prepare", "future", "prepared")

    def __init__(self, context: T, stamp_ns: int, prepare: Callable[[], PreparedInput]) -> None:
        self.context, self.stamp_ns, self.prepare = context, stamp_ns, prepare
        self.future: Future | None = None
        self.prepared: PreparedInput | None = None

    def steal(self) -> bool:
        """Prepare here when no worker has started it; True when it is prepared now."""
        if self.prepared is not None:
            return True
        if self.future is None or self.future.cancel():
            self.prepared = self.prepare()
            return True
        return False

    def wait(self) -> PreparedInput:
        if self.prepared is None:
            self.prepared = self.future.result()
        return self.prepared


class FramePipeline(Generic[T]):
    """Frames put in order, taken back decided in the same order (see the module doc).

    loop: the frame loop whose processor decides (its counters count each frame at `take`).
    depth: frames in flight at most (default 2 x workers, 1 with one worker: each frame is decided
        as soon as it is put, as before); `full` says when to take one first.
    before: called with a frame's context just before it is decided (e.g. to switch maps).
    Use as a context manager: leaving it stops the threads (frames not taken are dropped).
    """

    def __init__(self, loop: FrameLoop, workers: int = 1, depth: int | None = None,
                 before: Callable[[T], None] | None = None) -> None:
        self.loop = loop
        self.before = before
        self.workers = check_workers(workers)
        if self.workers > 1 and not loop.prepares:
            raise ConfigError("--workers above 1 needs a detector that prepares frames apart (LoopClosureDetector)")
        self.depth = max(1, depth if depth is not None else 2 * self.workers if self.workers > 1 else 1)
        self._pool = ThreadPoolExecutor(self.workers - 1, thread_name_prefix="aefabmap-frame") \
            if self.workers > 1 else None
        self._opencv_threads = self._switch_interval = None
        if self._pool is not None:
            self._opencv_threads = cv2.getNumThreads()
            cv2.setNumThreads(1)
            self._switch_interval = sys.getswitchinterval()
            sys.setswitchinterval(max(self._switch_interval, SWITCH_INTERVAL_S))
        self._jobs: deque[_Job[T]] = deque()
        # One worker: each frame is decoded and processed at its turn, exactly as FrameLoop.step does.
        self._extract = self.workers > 1

    def __enter__(self) -> FramePipeline[T]:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def close(self) -> None:
        """Stop the threads; frames not taken are not decided."""
        for job in self._jobs:
            if job.future is not None:
                job.future.cancel()
        self._jobs.clear()
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
        if self._opencv_threads is not None:
            cv2.setNumThreads(self._opencv_threads)
            self._opencv_threads = None
        if self._switch_interval is not None:
            sys.setswitchinterval(self._switch_interval)
            self._switch_interval = None

    @property
    def pending(self) -> int:
        """Frames put and not yet taken."""
        return len(self._jobs)

    @property
    def full(self) -> bool:
        return len(self._jobs) >= self.depth

    def put_payload(self, context: T, payload, encoding: str, stamp_ns: int) -> None:
        self._put(_Job(context, stamp_ns, lambda: self.loop.prepare_payload(payload, encoding, self._extract)))

    def put_file(self, context: T, path, stamp_ns: int) -> None:
        self._put(_Job(context, stamp_ns, lambda: self.loop.prepare_file(path, self._extract)))

    def put_prepared(self, context: T, prepared: PreparedInput, stamp_ns: int) -> None:
        """A frame with nothing to prepare (e.g. refused by its transport)."""
        job = _Job(context, stamp_ns, lambda: prepared)
        job.prepared = prepared
        self._jobs.append(job)

    def _put(self, job: _Job[T]) -> None:
        if self._pool is not None:
            job.future = self._pool.submit(job.prepare)
        self._jobs.append(job)

    def take(self) -> tuple[T, FrameOutcome]:
        """Decide the oldest frame put (waiting for its preparation; meanwhile the caller's
        thread prepares later frames no worker has started) and return its context and outcome."""
        if not self._jobs:
            raise ConfigError("no frame in the pipeline to take")
        oldest = self._jobs[0]
        while not oldest.steal() and not oldest.future.done():
            later = next((j for j in list(self._jobs)[1:] if j.prepared is None and j.future is not None
                          and not j.future.running() and not j.future.done()), None)
            if later is None or not later.steal():
                break
        prepared = oldest.wait()
        self._jobs.popleft()
        if self.before is not None:
            self.before(oldest.context)
        return oldest.context, self.loop.finish(prepared, oldest.stamp_ns)


def pipelined(loop: FrameLoop, files: Iterable[tuple[T, Any, int]], workers: int = 1) -> Iterator[tuple[T, FrameOutcome]]:
    """Decide every image file of `files`, (context, path, stamp_ns), in order, with `workers`
    threads (see the module doc); yields (context, outcome) as each is decided."""
    with FramePipeline(loop, workers) as pipe:
        for context, path, stamp_ns in files:
            pipe.put_file(context, path, stamp_ns)
            while pipe.full:
                yield pipe.take()
        while pipe.pending:
            yield pipe.take()
