"""ReplayStats: `run`'s stats message, due by the replayed capture stamps (not the wall clock)."""

from __future__ import annotations

import numpy as np

from aefabmap_runtime.adapters.frame_loop import FrameLoop
from aefabmap_runtime.adapters.replay_stats import ReplayStats
from aefabmap_runtime.core.records.messages import StatsMessage

from .stream_fakes import FakeDetector

S = 10**9


def _replay(stamps_s: list[float], period_s: float = 5.0) -> list[tuple[int, StatsMessage]]:
    """Frames at these stamps (s) through a real frame loop; the (stamp, message) pairs sent."""
    loop = FrameLoop(FakeDetector())
    sent: list[tuple[int, StatsMessage]] = []
    stats = ReplayStats(loop, period_s, lambda msg, data, stamp: sent.append((stamp, StatsMessage.from_json(data))))
    rng = np.random.default_rng(0)
    for t in stamps_s:
        stats.started()
        out = loop.step_image(rng.integers(0, 256, (48, 64), dtype=np.uint8), round(t * S))
        stats.decided(round(t * S), out.result is not None)
    stats.final()
    return sent


def test_one_message_per_period_of_replay_time_and_one_at_the_end():
    sent = _replay([i * 1.0 for i in range(12)])
    assert [stamp for stamp, _ in sent] == [5 * S, 10 * S, 11 * S]
    assert [m.frames_processed for _, m in sent] == [6, 11, 12]
    assert sent[-1][1].latency_ms.p50 is not None and sent[-1][1].rss_mb is not None


def test_a_long_pause_gives_one_message_and_a_stamp_going_back_starts_again():
    """A pause of 94 s in the log is one message, not 18; the next run of a log set (stamps back
    at 50 s) counts its period from its own first frame."""
    sent = _replay([0, 3, 6, 100, 101, 50, 53, 56])
    assert [stamp for stamp, _ in sent] == [6 * S, 100 * S, 56 * S, 56 * S]  # the last one: the end


def test_a_replay_without_frames_still_ends_with_a_message():
    sent = _replay([])
    assert len(sent) == 1 and sent[0][1].frames_processed == 0 and sent[0][1].latency_ms.p95 is None
