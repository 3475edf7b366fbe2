"""Which places the slam pipeline checks in 3-D for a frame whose two-view test gave no edge."""

from __future__ import annotations

from types import SimpleNamespace

from aefabmap.slam.pipeline import proposal_frames


def result(verified_frame, ranked_frames):
    """A detector result: verified (or not) to `verified_frame`, candidates in FAB-MAP rank order
    (given shuffled, as the detector may list them in checking order)."""
    cands = [SimpleNamespace(frame=f, rank=r) for r, f in enumerate(ranked_frames)]
    return SimpleNamespace(verified=verified_frame is not None, verified_frame=verified_frame,
                           candidates=cands[::-1])


def test_the_two_view_verified_place_is_checked_first_then_candidates_by_rank():
    """A two-view loop whose PnP failed still gets the 3-D check: it is the best-supported place."""
    assert proposal_frames(result(0, [7, 0, 12, 3]), 5) == [0, 7, 12, 3]
    assert proposal_frames(result(40, [7, 0]), 5) == [40, 7, 0]  # a tracked place, not a FAB-MAP candidate


def test_without_a_two_view_loop_the_candidates_go_by_rank_up_to_the_limit():
    assert proposal_frames(result(None, [9, 4, 2, 8, 1, 6]), 5) == [9, 4, 2, 8, 1]
    assert proposal_frames(result(0, [7, 0, 12]), 1) == [0]
    assert proposal_frames(result(0, [7, 0, 12]), 0) == []
