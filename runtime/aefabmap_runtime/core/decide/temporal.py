"""Temporal consistency of verified loop closures (pure).

Definition (consecutive agreement, the "temporal consistency" of DLoopDetector and the island
overlap of iBoW-LCD reduced to one number): a geometrically verified match of frame i to
frame j is *consistent* when each of the `frames` preceding query frames i-1, ..., i-frames
also had a geometrically verified match j' with |j' - j| <= `tolerance` frames (its island of
earlier frames overlaps). A frame with no verified match breaks the chain.

Effect: one lucky geometric match cannot raise a loop alone; the price is the first `frames`
frames of every revisit (the chain is still being built) and frames where the matches jump
between two earlier passes of the same place.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from aefabmap_runtime.errors import ConfigError, StateError
from aefabmap_runtime.core.records.map_state import MapState


class TemporalFilter:
    """Consecutive-agreement check over the last `frames` query frames.

    frames: preceding frames that must agree (0: every verified match passes).
    tolerance: largest difference, in frames, between agreeing matched frames.
    """

    def __init__(self, frames: int, tolerance: int) -> None:
        if frames < 0 or tolerance < 0:
            raise ConfigError(f"temporal frames and tolerance must be >= 0, got {frames}, {tolerance}")
        self.frames = frames
        self.tolerance = tolerance
        self._history: deque[int | None] = deque(maxlen=max(frames, 1))

    def update(self, matched_frame: int | None) -> bool:
        """Record this query's verified match (None: none) and say whether it is consistent."""
        ok = matched_frame is not None and (
            self.frames == 0
            or (
                len(self._history) == self.frames
                and all(h is not None and abs(h - matched_frame) <= self.tolerance for h in self._history)
            )
        )
        self._history.append(matched_frame)
        return bool(ok)

    def state(self) -> MapState:
        """The matched frames of the last queries, oldest first (-1: no verified match)."""
        return MapState({"history": np.array([-1 if h is None else h for h in self._history], np.int64)})

    def load_state(self, st: MapState) -> None:
        history = st.array("history", "iu", (None,), lo=-1)
        if history.size > self._history.maxlen:
            raise StateError(f"map state: temporal history holds {history.size} frames, at most {self._history.maxlen}")
        self._history.clear()
        self._history.extend(None if h < 0 else int(h) for h in history.tolist())

    def reset(self) -> None:
        self._history.clear()
