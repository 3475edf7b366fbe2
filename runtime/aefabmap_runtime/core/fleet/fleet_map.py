"""Other robots' places, held beside the own map and verified like its own (pure).

A node of a fleet (runtime/aefabmap_runtime/adapters/fleet.py) hands `FleetMap` the place summaries other robots
publish. Each remote robot gets its own FAB-MAP scorer (runtime/aefabmap_runtime/core/rank/scorer.py) built as the
detector builds its own, so its places are ranked against the same new-place model; its frame
numbers never mix with another robot's. The detector holds the FleetMap as its second candidate
source (LoopClosureDetector.attach_remote): when its own map verified nothing for a frame,
`FleetMap.match` ranks every remote robot's places, takes each robot's best `top_k`,
gets their keypoints (a cache, else the caller's fetch, which may fail) and verifies them as the
own places are verified, against a bar stricter by the log10 of the number of remote pairs
checked (each is one more chance of a false alarm). The own map comes first: remote places live
in what the own map leaves of `max_places` / `memory_mb` and of the fleet's own caps, the oldest
arrival evicted first. A summary of a new map epoch (the robot restarted: its frame numbers
mean other places now) makes the map forget that robot's places and cached keypoints first, and
names the robot in `restarted` so that the node asks it for all its places again.
"""

from __future__ import annotations

import math
from collections import OrderedDict, deque
from dataclasses import dataclass
from typing import Callable

import numpy as np

from aefabmap_runtime.errors import ConfigError
from aefabmap_runtime.core.fleet.fleet_wire import PlaceSummary, check_token
from aefabmap_runtime.core.map.keypoint_store import PlaceKeypoints
from aefabmap_runtime.core.records.messages import RemoteRobotStats
from aefabmap_runtime.core.rank.scorer import Scorer
from aefabmap_runtime.core.verify.verification import GeometryResult

#: Fetch latencies kept per robot for the stats' median (ms).
_LATENCIES_KEPT = 200


@dataclass(frozen=True)
class FleetConfig:
    """A node's part in a fleet.

    name: the fleet (a key-expression token); robot: this node's id in it (same rules).
    fetch_timeout_ms: how long a keypoint fetch may wait for the robot that owns the place.
    top_k: remote places checked per robot and frame (FAB-MAP's best first).
    track, track_memory: the temporal prior after a loop to another robot's place, as the own
        map's (CandidateConfig.track, track_memory): its next frames are tried first. Without the
        own map's reach around them, the memory stays short.
    max_robots: remote robots kept; summaries of further robots are refused and counted.
    max_places: remote places kept in all (besides the caps the own map leaves).
    cache_places: fetched keypoint sets kept for the next frames (a revisit checks the same places).
    """

    name: str = ""
    robot: str = ""
    fetch_timeout_ms: int = 300
    top_k: int = 2
    track: int = 2
    track_memory: int = 3
    max_robots: int = 16
    max_places: int = 100_000
    cache_places: int = 64

    def __post_init__(self) -> None:
        check_token(self.name, "fleet name")
        check_token(self.robot, "robot id")
        for name, lo, hi in (("fetch_timeout_ms", 1, 60_000), ("top_k", 1, 20), ("track", 0, 20),
                             ("track_memory", 1, 20), ("max_robots", 1, 1000),
                             ("max_places", 1, 10_000_000), ("cache_places", 1, 100_000)):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or not lo <= value <= hi:
                raise ConfigError(f"fleet {name} must be an integer in [{lo}, {hi}], got {str(value)[:40]}")


class RemoteRobot:
    """One robot's places: a scorer of their words, the place id <-> frame tables, the latest
    frame it offered (-1: none; a catch-up asks for the ones after it), the map epoch they belong
    to, its counters and its recent fetch latencies (ms)."""

    def __init__(self, scorer: Scorer, epoch: int) -> None:
        self.scorer = scorer
        self.epoch = epoch
        self.frame_of: dict[int, int] = {}
        self.place_of: dict[int, int] = {}
        self.last_frame = -1
        self.stats = RemoteRobotStats()
        self.fetch_ms: deque[float] = deque(maxlen=_LATENCIES_KEPT)

    def refuse(self, reason: str) -> None:
        self.stats.refused[reason] = self.stats.refused.get(reason, 0) + 1


@dataclass
class RemoteMatch:
    """A verified loop to another robot's place."""

    robot: str
    frame: int
    geometry: GeometryResult
    checked: int


class FleetMap:
    """Remote robots' places within caps; see the module doc.

    make_scorer: a fresh, empty scorer like the own map's (LoopClosureDetector.new_scorer).
    room: (places, bytes) the own map leaves for remote places now (None: no such cap; PlaceMap.room).
    """

    def __init__(self, config: FleetConfig, make_scorer: Callable[[], Scorer],
                 room: Callable[[], tuple[int | None, int | None]]) -> None:
        self.config = config
        self._make_scorer, self._room = make_scorer, room
        self.robots: dict[str, RemoteRobot] = {}
        self._arrivals: deque[tuple[str, int]] = deque()  # (robot, frame), oldest first
        self._cache: OrderedDict[tuple[str, int], PlaceKeypoints] = OrderedDict()
        self.evicted = 0
        #: Refusals of messages from robots the map does not hold (unreadable, other bundle, one
        #: robot too many), by reason: per-robot counters would let a peer grow them without bound.
        self.refused_elsewhere: dict[str, int] = {}
        #: Robots whose map epoch changed since the caller last emptied this list.
        self.restarted: list[str] = []
        self._track: tuple[str, int, int] | None = None  # (robot, frame, query sequence) of the last loop

    def epoch(self, robot: str) -> int:
        """The map epoch of `robot`'s places held (0 when none are)."""
        held = self.robots.get(robot)
        return held.epoch if held is not None else 0

    def last_frame(self, robot: str) -> int:
        """The latest frame `robot` offered this node (-1: none yet)."""
        held = self.robots.get(robot)
        return held.last_frame if held is not None else -1

    @property
    def n_places(self) -> int:
        return sum(r.scorer.n_alive for r in self.robots.values())

    def nbytes(self) -> int:
        """Scorer memory of the remote places plus the cached keypoints."""
        return sum(r.scorer.nbytes() for r in self.robots.values()) + sum(p.nbytes for p in self._cache.values())

    def add(self, summary: PlaceSummary) -> bool:
        """Keep a remote place; False (counted under a reason) when it is refused."""
        if summary.robot == self.config.robot:
            return False  # our own summaries, back through a router: not a remote place
        robot = self.robots.get(summary.robot)
        if robot is None:
            if len(self.robots) >= self.config.max_robots:
                self.refuse(summary.robot, "too_many_robots")
                return False
            robot = self.robots[summary.robot] = RemoteRobot(self._make_scorer(), summary.epoch)
        elif summary.epoch != robot.epoch:
            self._forget(summary.robot, summary.epoch)
        robot.stats.summaries += 1
        robot.last_frame = max(robot.last_frame, summary.frame)
        if summary.frame in robot.place_of:
            return False  # held already: a catch-up's replies may overlap what arrived live
        if summary.words.size == 0:
            robot.refuse("no_words")
            return False
        pid = robot.scorer.add(summary.words)
        robot.frame_of[pid], robot.place_of[summary.frame] = summary.frame, pid
        self._arrivals.append((summary.robot, summary.frame))
        self.fit()
        return summary.frame in robot.place_of

    def refuse(self, robot: str | None, reason: str) -> None:
        """Count a message refused before it reached the map (undecodable, other bundle), under
        its robot when the map holds that robot, else in `refused_elsewhere`."""
        if robot in self.robots:
            self.robots[robot].refuse(reason)
        else:
            self.refused_elsewhere[reason] = self.refused_elsewhere.get(reason, 0) + 1

    def fit(self) -> None:
        """Evict the oldest remote places until they fit the room the own map leaves."""
        places, nbytes = self._room()
        limit = self.config.max_places if places is None else min(self.config.max_places, max(places, 0))
        while self._arrivals and (self.n_places > limit or (nbytes is not None and self.nbytes() > nbytes)):
            self._evict_oldest()

    def _forget(self, name: str, epoch: int) -> None:
        """Drop a restarted robot's places and cached keypoints; from now on its places are of `epoch`."""
        robot = self.robots[name]
        for pid in robot.frame_of:
            robot.scorer.remove(pid)
        robot.frame_of.clear()
        robot.place_of.clear()
        for key in [k for k in self._cache if k[0] == name]:
            del self._cache[key]
        self._arrivals = deque(a for a in self._arrivals if a[0] != name)
        robot.epoch, robot.last_frame = epoch, -1
        robot.stats.map_restarts += 1
        if self._track is not None and self._track[0] == name:
            self._track = None
        self.restarted.append(name)

    def _evict_oldest(self) -> None:
        name, frame = self._arrivals.popleft()
        robot = self.robots.get(name)
        pid = robot.place_of.pop(frame, None) if robot is not None else None
        if pid is not None:
            robot.scorer.remove(pid)
            del robot.frame_of[pid]
            self._cache.pop((name, frame), None)
            self.evicted += 1

    def candidates(self, observed: np.ndarray) -> list[tuple[str, int]]:
        """(robot, frame) of each robot's top_k places for the observed words, best first per robot."""
        out = []
        for name, robot in self.robots.items():
            if robot.scorer.n_alive == 0:
                continue
            order = robot.scorer.rank(observed).order
            best = np.argsort(-order, kind="stable")[: self.config.top_k]
            out += [(name, robot.frame_of[int(p)]) for p in best if np.isfinite(order[p]) and int(p) in robot.frame_of]
        return out

    def keypoints(self, robot: str, frame: int, fetch: Callable[[str, int], PlaceKeypoints | None]) -> PlaceKeypoints | None:
        """The place's keypoints from the cache, else from fetch (kept in the cache when it gives them)."""
        key = (robot, frame)
        if key in self._cache:
            self._cache.move_to_end(key)
            return self._cache[key]
        place = fetch(robot, frame)
        if place is not None and robot in self.robots and frame in self.robots[robot].place_of:
            self._cache[key] = place
            while len(self._cache) > self.config.cache_places:
                self._cache.popitem(last=False)
            self.fit()
        return place

    def tracked(self, sequence: int) -> list[tuple[str, int]]:
        """The remote places the track expects for query `sequence` (nearest first), as the own
        map's track does (CandidateConfig.track): after a loop of query s to robot R's frame f,
        query s + lag expects R's frames f + lag, ..., f + lag + track - 1, then f + lag - 1,
        for lag up to track_memory; those R still holds."""
        if self._track is None:
            return []
        robot, frame, seq = self._track
        lag = sequence - seq
        held = self.robots.get(robot)
        if held is None or not 1 <= lag <= self.config.track_memory:
            return []
        expected = [frame + lag + i for i in range(self.config.track)] + [frame + lag - 1]
        return [(robot, f) for f in expected if f in held.place_of]

    def match(self, observed: np.ndarray, checker: Callable[[float], Callable[..., GeometryResult]],
              fetch: Callable[[str, int], PlaceKeypoints | None], max_log10_nfa: float,
              sequence: int = 0) -> RemoteMatch | None:
        """The most significant verified remote place for query `sequence`, or None.

        checker(bar) -> check(place, bruteforce, retry_only): the own detector's pair check
        (LoopClosureDetector.place_check) with the acceptance bar `bar` (log10 NFA). The tracked
        places (`tracked`) come first, each matched by words and retried all-pairs, and the
        first that passes is taken; else each FAB-MAP candidate is matched by words and each
        robot's best also retried all-pairs, as the own map's reach does. The bar is
        max_log10_nfa - log10(pair checks this frame may make).
        """
        tracked = self.tracked(sequence)
        wanted = [c for c in self.candidates(observed) if c not in tracked]
        if not wanted and not tracked:
            return None
        checks = 2 * len(tracked) + len(wanted) + len({r for r, _ in wanted})
        bar = max_log10_nfa - math.log10(checks)
        check = checker(bar)
        for robot, frame in tracked:
            place = self.keypoints(robot, frame, fetch)
            if place is None or len(place) == 0:
                continue
            g = check(place, False, False)
            if not g.verified:
                g = check(place, False, True)
            if g.verified:
                return self._matched(RemoteMatch(robot, frame, g, checks), sequence)
        best: RemoteMatch | None = None
        retried: set[str] = set()
        for robot, frame in wanted:
            place = self.keypoints(robot, frame, fetch)
            if place is None or len(place) == 0:
                continue
            g = check(place, False, False)
            if not g.verified and robot not in retried:
                retried.add(robot)
                g = check(place, False, True)
            if g.verified and (best is None or g.nfa < best.geometry.nfa):
                best = RemoteMatch(robot, frame, g, checks)
        return self._matched(best, sequence) if best is not None else None

    def _matched(self, match: RemoteMatch, sequence: int) -> RemoteMatch:
        self.robots[match.robot].stats.loops += 1
        self._track = (match.robot, match.frame, sequence)
        return match
