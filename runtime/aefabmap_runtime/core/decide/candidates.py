"""Candidate policy: which stored places one query frame is checked against, in what order, with
which matcher.

The detector ranks places (FAB-MAP log-likelihood or BoW similarity); this module turns that
ranking plus the track of recent verified matches into a sequence of pair checks and stops at
the first that passes. It judges nothing itself: each pair is judged by the verifier the caller
passes in (runtime/aefabmap_runtime/core/verify/verification.py). Why each rule exists and how it was measured:
docs/results.md, "Candidate policy".
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import numpy as np

from aefabmap_runtime.errors import ConfigError
from aefabmap_runtime.core.verify.verification import GeometryResult, more_significant

#: Largest `track_reach` accepted: each frame of the reach may cost a brute-force retry.
MAX_TRACK_REACH = 100

#: Where a checked place came from (Candidate.source on the wire).
SOURCES = ("track", "fabmap", "island")


@dataclass(frozen=True)
class CandidateConfig:
    """Which places a query is verified against. Every pair passes the same geometric test, but
    each extra check is one more chance for a wrong loop (chance, or real structure far down the
    same street: docs/results.md, "Candidate policy").

    top_k: FAB-MAP candidates (best log-likelihood first) tried per frame; the first that passes
        is taken, so a true loop usually costs one check.
    bruteforce_fallback: the best `bruteforce_fallback` FAB-MAP candidates get a second try with
        all-pairs descriptor matching when same-word matching did not pass (true matches split
        across words by quantisation, the more so under viewpoint and light change). The default
        retries every candidate of `top_k`.
    retry_alone: FAB-MAP's candidates that get the brute-force retry are checked by it alone (its
        all-pairs matches), without the same-word check first; False checks them by same-word
        matching first, as the tracked places always are. For a candidate FAB-MAP proposes, the
        retry decides whenever the same-word check fails, which is most of the time: on the
        training revisits, by day and at night, the same-word check before it changed no decision,
        while it cost a geometry fit per candidate of every frame that is not a loop
        (docs/results.md, "A frame's cost by its decision"). A tracked place keeps it: a revisit
        that goes on mostly passes it, the cheaper check.
    bruteforce_track: the same retry for every tracked place (see `track`).
    track: temporal prior: when the previous query was verified to stored frame f, the stored
        frames f+1, ..., f+`track`, then f, are tried before FAB-MAP's candidates (f-1, ...,
        f-`track`, then f, when the revisit runs backwards: `track_direction`). 0 disables.
    track_memory: the prior lasts this many query frames after the last verified match (frame
        i - lag verified to f: frames f+lag, ..., f+lag+track-1, f+lag-1 are tried). The default,
        twice `track_reach`, keeps the true frame within the reach of the expected one for the
        whole memory while the revisit moves at 0.5-1.5 times the first pass's speed.
    track_reach: when the track window and every FAB-MAP candidate failed, the other stored
        frames within track_reach of the expected frame are tried, nearest first (ahead before
        behind), each with the brute-force retry (`bruteforce_track`). 0 disables.
    track_direction: the track learns which way the revisit runs through the stored frames (a
        route driven back runs backwards): the side of the track's first match on which its
        latest lies (`Track`). Until a match lies off the first one, the frames a revisit would
        reach either way, f+lag and f-lag, are both checked and the more significant is taken.
        False: the track expects every revisit to run forwards, as logs and maps recorded
        before it ran (docs/results.md, "A revisit driven the other way").
    island: each of the best `island_candidates` FAB-MAP candidates that fails is followed by its
        stored temporal neighbours within +-`island` frames, nearest first. 0 disables.
    island_candidates: how many FAB-MAP candidates (best first) get island neighbours.
    max_trials: cap on places verified per frame (None: no cap), bounding the worst-case cost.
    max_bruteforce: cap on places per frame given the brute-force retry (None: no cap).
    margin_log10_nfa: a pair that passes is taken only when every other place checked for the
        query whose stored frame is more than one frame from its own has a log10 NFA at least
        this much higher (`tied_rival`; 0: no such check). The single-pair bound says that a
        revisit is there, not which stored frame it is: stored frames of one street share their
        far scene, and a query can have like evidence for two of them, of which the one that
        passes may be the wrong one (the other failed an inlier floor, say). By default log10 2,
        as for chains (runtime/aefabmap_runtime/core/decide/sequence.py): the pair taken is at
        least twice as unlikely by chance as any such rival; closer is a tie, and the query is
        left unpublished (docs/results.md, "A tie between two stored frames").
    """

    top_k: int = 5
    bruteforce_fallback: int = 5
    retry_alone: bool = True
    bruteforce_track: bool = True
    track: int = 2
    track_memory: int = 6
    track_reach: int = 3
    island: int = 0
    island_candidates: int = 1
    max_trials: int | None = None
    max_bruteforce: int | None = None
    margin_log10_nfa: float = math.log10(2.0)  # a factor of two, as for chains
    track_direction: bool = True

    def __post_init__(self) -> None:
        if self.top_k < 1:
            raise ConfigError(f"candidates top_k must be >= 1, got {self.top_k}")
        if self.bruteforce_fallback < 0:
            raise ConfigError(f"candidates bruteforce_fallback must be >= 0, got {self.bruteforce_fallback}")
        if self.track_memory < 1:
            raise ConfigError(f"candidates track_memory must be >= 1, got {self.track_memory}")
        if self.track < 0 or self.island < 0 or self.island_candidates < 0:
            raise ConfigError(f"candidates track and island must be >= 0, got {self.track}, {self.island}")
        if not (0 <= self.track_reach <= MAX_TRACK_REACH):
            raise ConfigError(f"candidates track_reach must lie in [0, {MAX_TRACK_REACH}], got {self.track_reach}")
        if self.max_trials is not None and self.max_trials < 1:
            raise ConfigError(f"candidates max_trials must be None or >= 1, got {self.max_trials}")
        if self.max_bruteforce is not None and self.max_bruteforce < 0:
            raise ConfigError(f"candidates max_bruteforce must be None or >= 0, got {self.max_bruteforce}")
        if not (np.isfinite(self.margin_log10_nfa) and self.margin_log10_nfa >= 0.0):
            raise ConfigError(f"candidates margin_log10_nfa must be finite and >= 0, got {self.margin_log10_nfa}")


#: check(place id, bruteforce, retry_only, upright) -> the pair's GeometryResult, or None when the
#: place holds no keypoints. retry_only: the brute-force retry alone (the place's same-word check
#: already failed in this query, or CandidateConfig.retry_alone skips it). upright: a failed
#: brute-force retry is retried with upright descriptors (VerificationConfig.upright); the policy
#: asks it for tracked places only.
PairCheck = Callable[[int, bool, bool, bool], "GeometryResult | None"]


@dataclass
class Attempt:
    """One pair check: the place, where it came from (SOURCES) and its result."""

    place: int
    source: str
    result: GeometryResult


@dataclass
class Search:
    """Outcome of one query's candidate search.

    best: the accepted check, else the most significant one (None: nothing checked);
    tried: places verified (a retry of the same place counts once); bruteforce: places given
    the brute-force retry; attempts: every check in order.
    """

    best: GeometryResult | None = None
    best_place: int | None = None
    source: str | None = None
    tried: int = 0
    bruteforce: int = 0
    attempts: list[Attempt] = field(default_factory=list)

    @property
    def verified(self) -> bool:
        return self.best is not None and bool(self.best.verified)


class Track:
    """The last geometrically verified match, (query sequence, stored frame); the stored frame
    of the track's first match (`anchor`); and which way the revisit runs through the stored
    frames: +1 the way they were recorded, -1 the other way, 0 not known yet. Part of the map
    state.

    learn: the direction is learnt (CandidateConfig.track_direction); otherwise it stays +1.
    """

    def __init__(self, learn: bool = True) -> None:
        self.learn = learn
        self.seq = -2
        self.frame = -1
        self.anchor = -1
        self.direction = 0 if learn else 1

    def expected(self, seq: int, memory: int) -> int | None:
        """The stored frame the track expects query `seq` to match (forwards while the direction
        is not known), or None when it has lapsed."""
        lag = seq - self.seq
        return self.frame + (self.direction or 1) * lag if 1 <= lag <= memory else None

    def confirm(self, seq: int, frame: int, memory: int, reach: int) -> None:
        """Query `seq` verified to stored `frame`. A match within `memory` queries of the last one
        and within `reach` of where the track would reach either way continues the track: the
        direction is the side of the track's first match on which it lies (where the revisit has
        gone since it began, so that a true match a frame or two behind the last one, as where
        stored frames look alike, does not turn it round). Any other match starts a new track,
        whose direction is not known."""
        if self.learn:
            lag = seq - self.seq
            if 1 <= lag <= memory and min(abs(frame - self.frame - lag), abs(frame - self.frame + lag)) <= reach:
                if frame != self.anchor:
                    self.direction = 1 if frame > self.anchor else -1
            else:
                self.anchor, self.direction = frame, 0
        self.seq, self.frame = seq, frame


class _Query:
    """Bookkeeping of one query's search: which places were checked and how, within the caps."""

    def __init__(self, config: CandidateConfig, ranking: np.ndarray, check: PairCheck) -> None:
        self.config = config
        self.ranking = ranking
        self.check = check
        self.search = Search()
        self.tried: dict[int, bool] = {}  # place id -> whether its check included the brute-force retry
        self.cap = config.max_trials if config.max_trials is not None else np.inf
        self.bf_cap = config.max_bruteforce if config.max_bruteforce is not None else np.inf

    @property
    def exhausted(self) -> bool:
        return self.search.tried >= self.cap

    def attempt(self, pid: int, source: str, bruteforce: bool = False) -> bool:
        """Check place `pid` unless it was checked already (a same-word check may still get the
        retry) or a cap is reached; True when it passes."""
        s = self.search
        bruteforce = bruteforce and s.bruteforce < self.bf_cap
        done = self.tried.get(pid)
        if done or (done is not None and not bruteforce) or self.exhausted or not np.isfinite(self.ranking[pid]):
            return False
        self.tried[pid] = bruteforce
        first = done is None
        # A place checked by same-word matching already gets the retry alone; so does FAB-MAP's
        # candidate given the retry, under `retry_alone`.
        retry_only = not first or (bruteforce and source == "fabmap" and self.config.retry_alone)
        # Upright descriptors only extend a verified loop (its track's window and reach): a new
        # loop is opened by the oriented test alone. On repetitive structure seen from the same
        # viewpoint (door frames along a corridor), upright descriptors of different places match
        # more often than the a-contrario background assumes (docs/results.md, "Upright
        # descriptors in the retry").
        g = self.check(pid, bruteforce, retry_only, source == "track")
        if g is None:
            return False
        s.bruteforce += bruteforce
        if first:
            s.tried += 1
        s.attempts.append(Attempt(pid, source, g))
        if more_significant(g, s.best):
            s.best, s.best_place, s.source = g, pid, source
        return bool(g.verified)

    def attempt_all(self, pids: Iterable[int], source: str, bruteforce: bool = False) -> bool:
        """The places in order; True at the first that passes."""
        return any(self.attempt(int(p), source, bruteforce) for p in pids)


class CandidatePolicy:
    """Chooses and orders the places one query is checked against (not thread-safe).

    Order, the first that passes is taken: the tracked places (stored frames following the last
    verified match), then FAB-MAP's top_k places, each failed one among the first
    `island_candidates` followed by its island neighbours, then, during a track, the other stored
    frames within `track_reach` of the expected one, each with the brute-force retry. A place is
    checked at most once per query, except that one checked by same-word matching only gets the
    retry alone when the track's reach comes to it.
    """

    def __init__(self, config: CandidateConfig | None = None) -> None:
        self.config = config or CandidateConfig()
        self.track = Track(self.config.track_direction)

    def search(self, seq: int, top: np.ndarray, ranking: np.ndarray, place_frames: np.ndarray,
               stored: Callable[[int], bool], check: PairCheck) -> Search:
        """Run the checks of query `seq`.

        top: FAB-MAP's best place ids, best first; ranking: (n_places,) log-likelihood or
        similarity of every place id (-inf: removed); place_frames: (n_places,) frame that made
        each place id (-1: none); stored: whether a place id holds keypoints.
        """
        c = self.config
        q = _Query(c, ranking, check)
        expect = self.track.expected(seq, c.track_memory)
        tracking = expect is not None and c.track > 0

        def tracked(frames: Iterable[int]) -> bool:
            return any(q.attempt_all(_places_of_frame(place_frames, f, stored), "track", c.bruteforce_track)
                       for f in frames if f >= 0)  # a track near the map's first frame reaches before it

        d, passed = self.track.direction, False
        if tracking and d:
            passed = tracked([*(expect + d * k for k in range(c.track)), expect - d])
        elif tracking:
            # A new track: the revisit may run either way. The frames it would reach forwards and
            # backwards are both checked; the more significant is taken (Search.best), and a tie
            # between them leaves the query unpublished (`tied_rival`).
            mirror = 2 * self.track.frame - expect
            passed = tracked([expect]) | tracked([mirror])  # both checked, not short-circuited
            passed = passed or tracked([*(x for k in range(1, c.track) for x in (expect + k, mirror - k)),
                                        *dict.fromkeys((expect - 1, mirror + 1))])
        if not passed:
            for rank, pid in enumerate(top):
                if not np.isfinite(ranking[pid]) or q.exhausted:
                    break  # removed places (-inf) sort last
                if q.attempt(int(pid), "fabmap", rank < c.bruteforce_fallback):
                    break
                if c.island and rank < c.island_candidates and \
                        q.attempt_all(_island(place_frames, int(pid), c.island), "island"):
                    break
        if tracking and c.track_reach and not q.search.verified:
            # The window and FAB-MAP's candidates failed: the last verified match places the robot
            # only roughly, so the revisit's true frame may lie a little outside the window.
            ahead = d or 1
            tracked(sorted(range(expect - c.track_reach, expect + c.track_reach + 1),
                           key=lambda f: (abs(f - expect), ahead * (f - expect) < 0)))
        return q.search


def tied_rival(search: Search, place_frames: np.ndarray, margin_log10_nfa: float) -> Attempt | None:
    """The most significant check of `search` that ties with its passing pair, or None.

    A tie: a place whose stored frame (place_frames: (n_places,) frame of each place id) lies
    more than one frame from the passing place's, with a finite log10 NFA below the passing
    pair's plus `margin_log10_nfa` (CandidateConfig.margin_log10_nfa), whether it passed or not.
    None as well when nothing passed or the margin is 0.
    """
    if not search.verified or search.best_place is None or margin_log10_nfa <= 0.0:
        return None
    frame, bar = int(place_frames[search.best_place]), float(search.best.nfa) + margin_log10_nfa
    rivals = [a for a in search.attempts if abs(int(place_frames[a.place]) - frame) > 1
              and np.isfinite(a.result.nfa) and a.result.nfa < bar]
    return min(rivals, key=lambda a: a.result.nfa) if rivals else None


def _places_of_frame(place_frames: np.ndarray, frame: int, stored: Callable[[int], bool]) -> list[int]:
    """Stored place ids made by `frame`."""
    return [int(p) for p in np.flatnonzero(place_frames == frame) if stored(int(p))]


def _island(place_frames: np.ndarray, pid: int, radius: int) -> list[int]:
    """Places made within +-radius frames of place pid's frame, nearest first, pid excluded."""
    f = int(place_frames[pid])
    pids = np.flatnonzero((np.abs(place_frames - f) <= radius) & (place_frames >= 0))
    pids = pids[np.argsort(np.abs(place_frames[pids] - f), kind="stable")]
    return [int(p) for p in pids if int(p) != pid]


def top_places(ranking: np.ndarray, k: int) -> np.ndarray:
    """Ids of the k best places of `ranking` (n,), best first, stable among ties; removed places
    (-inf) sort last and are included only when fewer than k places remain."""
    k = min(k, ranking.size)
    if k <= 0:
        return np.zeros(0, np.int64)
    if k < ranking.size:
        # argpartition's choice and order among ties differ between machines (x86-64 / aarch64
        # numpy): take the places above the k-th value, then the lowest ids equal to it.
        kth = -np.partition(-ranking, k - 1)[k - 1]
        above = np.flatnonzero(ranking > kth)
        top = np.concatenate([above, np.flatnonzero(ranking == kth)[: k - above.size]])
        top.sort()
    else:
        top = np.arange(ranking.size)
    return top[np.argsort(-ranking[top], kind="stable")]
