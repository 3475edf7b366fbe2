"""Evidence over consecutive frames: a run of query frames matching a run of stored frames (pure).

A revisit seen through a changed viewpoint often gives each frame some geometric evidence for the
right place, but not enough for one pair to pass `VerificationConfig.max_log10_nfa`. A robot
moves continuously, so consecutive query frames of a revisit match stored frames that are close
to one another. A *chain* is `frames` consecutive query frames, each with a checked place whose
best model reaches log10 NFA < `link_log10_nfa`, whose stored frames differ by at most
`tolerance` from one query to the next. The chain's evidence is the sum of its links' log10 NFA;
the last frame is accepted when the sum is below `max_log10_nfa`.

Why the bound (docs/results.md, "Evidence over consecutive frames"): if the links were
independent under the null hypothesis, each link's NFA bounds the chance of its evidence, and
the product of `frames` such chances s has P(product <= s) = s * sum_{i<frames} (-ln s)^i / i!.
One query forms at most (checked places) x (2 * tolerance + 1)^(frames - 1) chains. Asking
that to be as unlikely as one pair at the single-pair bound (-4) gives the default -7 for
two frames (-4, minus log10 of a handful of checked places x 7 alignments, minus log10 of
1 - ln s at s = 1e-7). Consecutive frames are not independent under the null (repetitive
structure repeats), which is why the bound is checked against chains between different drives
of the training set (scripts/calibrate_sequence.py).

The bound says a revisit is there, not which stored frame it is. Stored frames of one stretch of
road share their far scene, so a query may have links of like evidence to two of them that are not
neighbours, and the choice between them would be a coin toss (docs/results.md, "A tie between two
stored frames"). A chain is therefore accepted only when every chain ending at a stored frame more
than one frame from its own is at least `margin_log10_nfa` less significant: by default log10 2,
so the accepted chain is at least twice as unlikely by chance as any such rival; closer is a tie.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from aefabmap_runtime.errors import ConfigError, StateError
from aefabmap_runtime.core.records.map_state import MapState

#: Links one query keeps (its most significant ones): bounds the work and the map state.
MAX_LINKS = 64


@dataclass(frozen=True)
class SequenceConfig:
    """Evidence over consecutive frames (module docstring).

    frames: consecutive query frames a chain spans (0: off; 1 would be the single-pair test).
    tolerance: largest difference, in stored frames, between the links of consecutive queries.
    link_log10_nfa: a checked place is a link when its best model's log10 NFA is below this.
    max_log10_nfa: a chain is accepted when the sum of its links' log10 NFA is below this.
    margin_log10_nfa: ... and when every chain ending at a stored frame more than one frame from
        the accepted chain's last stored frame sums at least this much more (0: no such check).
    """

    frames: int = 2
    tolerance: int = 3
    link_log10_nfa: float = 0.0
    max_log10_nfa: float = -7.0
    margin_log10_nfa: float = math.log10(2.0)  # a factor of two (module docstring)

    def __post_init__(self) -> None:
        if self.frames < 0 or self.frames == 1 or self.frames > 16:
            raise ConfigError(f"sequence frames must be 0 (off) or in [2, 16], got {self.frames}")
        if self.tolerance < 0:
            raise ConfigError(f"sequence tolerance must be >= 0 frames, got {self.tolerance}")
        if not (np.isfinite(self.link_log10_nfa) and np.isfinite(self.max_log10_nfa)
                and np.isfinite(self.margin_log10_nfa)):
            raise ConfigError("sequence link_log10_nfa, max_log10_nfa and margin_log10_nfa must be finite")
        if self.margin_log10_nfa < 0.0:
            raise ConfigError(f"sequence margin_log10_nfa must be >= 0, got {self.margin_log10_nfa}")
        if self.link_log10_nfa > 0.0 or self.max_log10_nfa > self.link_log10_nfa:
            raise ConfigError("sequence needs max_log10_nfa <= link_log10_nfa <= 0")


@dataclass(frozen=True)
class Link:
    """A checked place of one query: its id, the stored frame that made it, its best log10 NFA."""

    place: int
    frame: int
    log10_nfa: float


class SequenceEvidence:
    """Chains of links over the last `frames` queries (not thread-safe; part of the map state)."""

    def __init__(self, config: SequenceConfig) -> None:
        self.config = config
        # Links of the previous frames - 1 queries, most recent last: (stored frame, log10 NFA) arrays.
        self._history: deque[tuple[np.ndarray, np.ndarray]] = deque(maxlen=max(config.frames - 1, 1))

    def update(self, links: list[Link]) -> tuple[Link, float] | None:
        """Record this query's links; return the link ending the most significant accepted chain
        and the chain's summed log10 NFA, or None (no chain of `frames` queries passes, or one
        ending at a stored frame that is not a neighbour of its own comes within the margin)."""
        c = self.config
        links = sorted((x for x in links if x.log10_nfa < c.link_log10_nfa), key=lambda x: x.log10_nfa)[:MAX_LINKS]
        frames = np.array([x.frame for x in links], np.int64)
        nfa = np.array([x.log10_nfa for x in links], np.float64)
        best = None
        if links and len(self._history) == c.frames - 1:
            total = self._chain_sums(frames, nfa)
            i = int(np.argmin(total))
            rivals = total[np.abs(frames - frames[i]) > 1]
            if total[i] < c.max_log10_nfa and not np.any(rivals < total[i] + c.margin_log10_nfa):
                best = (links[i], float(total[i]))
        self._history.append((frames, nfa))
        return best

    def _chain_sums(self, frames: np.ndarray, nfa: np.ndarray) -> np.ndarray:
        """(L,) smallest chain sum ending at each of this query's links (inf: no chain)."""
        tol = self.config.tolerance
        # Best sum of a chain over the recorded queries ending at each link of the oldest, then onwards.
        run_frames, run_sums = self._history[0]
        for past_frames, past_nfa in list(self._history)[1:] + [(frames, nfa)]:
            run_sums = _extend(run_frames, run_sums, past_frames, past_nfa, tol)
            run_frames = past_frames
        return run_sums

    def state(self) -> MapState:
        """The recorded links: per past query (oldest first) its count, then all frames and NFAs."""
        counts = np.array([f.size for f, _ in self._history], np.int64)
        frames = np.concatenate([f for f, _ in self._history]) if self._history else np.zeros(0, np.int64)
        nfa = np.concatenate([n for _, n in self._history]) if self._history else np.zeros(0, np.float64)
        return MapState({"counts": counts, "frames": frames.astype(np.int64), "nfa": nfa.astype(np.float64)})

    def load_state(self, st: MapState) -> None:
        counts = st.array("counts", "iu", (None,), lo=0)
        frames = st.array("frames", "iu", (None,), lo=-1)
        nfa = st.array("nfa", "f", (None,))
        if counts.size > self._history.maxlen or counts.sum() != frames.size or frames.size != nfa.size \
                or (counts > MAX_LINKS).any() or not np.all(nfa < self.config.link_log10_nfa):
            raise StateError("map state: sequence links do not fit this detector's settings")
        self._history.clear()
        for start, n in zip(np.cumsum(counts) - counts, counts, strict=True):
            self._history.append((frames[start: start + n].copy(), nfa[start: start + n].copy()))

    def reset(self) -> None:
        self._history.clear()


def _extend(prev_frames: np.ndarray, prev_sums: np.ndarray, frames: np.ndarray, nfa: np.ndarray,
            tol: int) -> np.ndarray:
    """Chain sums ending at each link (frames, nfa) of a query, from the chain sums ending at the
    links of the query before it: its own log10 NFA plus the best reachable one (inf: none)."""
    if frames.size == 0 or prev_frames.size == 0:
        return np.full(frames.size, np.inf)
    reach = np.abs(frames[:, None] - prev_frames[None, :]) <= tol
    best_prev = np.where(reach, prev_sums[None, :], np.inf).min(axis=1)
    return nfa + best_prev
