"""The live run's periodic stats, for a replay: a StatsMessage every stats period of replay time.

`aefabmap run` sends a StatsMessage (runtime/aefabmap_runtime/core/records/messages.py) every
``stats_period_s`` seconds and at its end (runtime/aefabmap_runtime/adapters/node.py
StatsEmitter). A replay plays the log's time, not the wall clock's (``--rate X``: X times faster;
``--rate 0``: as fast as it can), so :class:`ReplayStats` sends one each time the replayed capture
stamps have advanced by ``period_s``, and one at the end, each with the stamp of the frame that
made it due as its time on the view (where the results are plotted): at ``--rate 1`` they come
as the live run's did, and at any rate they fall where the live run's fall on the log's time
line. A stamp going back (the next run of a log set) starts the count again.

Fields as in `run`: the frame loop's counters; ``latency_ms``: percentiles over the last
LATENCY_WINDOW frames of frame handed to the pipeline -> result (decode + detector, as the
node's ring -> result), ms; ``fps``: frames processed per wall-clock second since the previous
message; ``uptime_s``: wall-clock seconds since the replay started; ``rss_mb``: this process.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable

import numpy as np

from aefabmap_runtime.adapters.frame_loop import FrameLoop
from aefabmap_runtime.core.records.messages import FleetStats, LatencySummary, StatsMessage

#: Frames whose latency the percentiles cover (as the node's).
LATENCY_WINDOW = 2000


def _percentile(values, q: float) -> float | None:
    return float(np.percentile(np.fromiter(values, dtype=np.float64), q)) if values else None


class ReplayStats:
    """Stats of a replay for ``send(message, its JSON bytes, stamp_ns)`` (see the module docstring).

    Call ``started()`` as each frame goes into the pipeline, ``decided(stamp_ns, has_result)`` as
    each comes out (in the same order), ``final()`` after the last one.
    """

    def __init__(self, loop: FrameLoop, period_s: float, send: Callable[[StatsMessage, bytes, int], None],
                 fleet_stats: Callable[[], FleetStats] | None = None) -> None:
        self.loop, self.period_ns, self.send, self.fleet_stats = loop, round(period_s * 1e9), send, fleet_stats
        self.sent = 0
        self._t0 = self._last_t = time.monotonic()
        self._last_n = 0
        self._started: deque[int] = deque()
        self._latencies_ms: deque[float] = deque(maxlen=LATENCY_WINDOW)
        self._due_ns: int | None = None
        self._stamp_ns: int | None = None

    def started(self) -> None:
        self._started.append(time.monotonic_ns())

    def decided(self, stamp_ns: int, has_result: bool) -> None:
        """One frame out of the pipeline (refused ones too); sends a message when one is due."""
        began = self._started.popleft() if self._started else None
        if has_result and began is not None:
            self._latencies_ms.append((time.monotonic_ns() - began) / 1e6)
        if self._due_ns is None or (self._stamp_ns is not None and stamp_ns < self._stamp_ns):
            self._due_ns = stamp_ns + self.period_ns
        elif stamp_ns >= self._due_ns:
            self._emit(stamp_ns)
            # As the node's emitter: a long pause in the log gives one message, not one per period.
            self._due_ns = max(self._due_ns + self.period_ns, stamp_ns + self.period_ns // 2)
        self._stamp_ns = stamp_ns

    def final(self) -> None:
        """The message at the end, at the last frame's stamp (no frame: now)."""
        self._emit(self._stamp_ns if self._stamp_ns is not None else time.time_ns())

    def _emit(self, stamp_ns: int) -> None:
        from aefabmap_runtime.adapters.health import rss_mb

        now = time.monotonic()
        fps = (self.loop.processed - self._last_n) / max(now - self._last_t, 1e-9)
        self._last_t, self._last_n = now, self.loop.processed
        rss = rss_mb()
        msg = self.loop.stats_message(
            uptime_s=now - self._t0, rss_mb=None if rss is None else round(rss, 1), fps=round(fps, 2),
            latency_ms=LatencySummary(_percentile(self._latencies_ms, 50), _percentile(self._latencies_ms, 95)),
        )
        msg.fleet = self.fleet_stats() if self.fleet_stats is not None else None
        self.sent += 1
        self.send(msg, msg.to_json_bytes(), stamp_ns)
