"""Other robots' places, held beside the own map and verified like its own (pure).

A node of a fleet (runtime/aefabmap_runtime/adapters/fleet.py) hands `FleetMap` the place summaries other robots
publish. Each remote robot gets its own FAB-MAP scorer (runtime/aefabmap_runtime/core/rank/scorer.py) built as the
detector builds its own, so its places are ranked against the same new-place model; its frame
numbers never mix with another robot's. The detector holds the FleetMap as its second candidate
source (LoopClosureDetector.attach_remote): when its own map verified nothing for a frame,
`FleetMap.match` ranks every remote robot's places, takes each robot's best `top_k`,
gets their keypoints (a cache, else the caller's fetch, which may fail) and verifies them as the
own places are verified, against a bar stricter by the log10 of the number of remote pairs
checked (each is one more chance of a false alarm). The keypoints a frame needs are asked for
in one batch (`Fetch`), so a frame waits for the slowest robot at most once. The own map comes
first: remote places live in what the own map leaves of `max_places` / `memory_mb` and of the
fleet's own caps; when they do not fit, the robot holding the most places loses its oldest, so
one robot's flood never evicts another's places. A summary of another map epoch is not believed
by itself (anyone may send one): it is refused and its robot named in `epoch_claims`, and only
`confirm_epoch`, which the node calls with what that robot's own session answered, makes the
map forget the robot's places; it then names the robot in `restarted` so that the node asks it
for all its places again. A robot is admitted only while the node sees its liveliness token
(`add(..., alive=)`); a full table makes room by dropping a robot whose token is gone.
"""

from __future__ import annotations

import math
from collections import OrderedDict, deque
from dataclasses import dataclass
from typing import Callable, Iterable

import numpy as np

from aefabmap_runtime.errors import ConfigError
from aefabmap_runtime.core.fleet.fleet_wire import PlaceSummary, check_token
from aefabmap_runtime.core.map.keypoint_store import PlaceKeypoints
from aefabmap_runtime.core.records.messages import RemoteRobotStats
from aefabmap_runtime.core.rank.scorer import Scorer
from aefabmap_runtime.core.verify.verification import GeometryResult

#: Fetch latencies kept per robot for the stats' median (ms).
_LATENCIES_KEPT = 200

#: Gets the keypoints of several remote places at once, within one deadline: {(robot, frame):
#: keypoints or None (not answered in time, refused, robot gone)}; may leave pairs out (None).
Fetch = Callable[[list[tuple[str, int]]], dict[tuple[str, int], PlaceKeypoints | None]]


@dataclass(frozen=True)
class FleetConfig:
    """A node's part in a fleet.

    name: the fleet (a key-expression token); robot: this node's id in it (same rules).
    fetch_timeout_ms: how long a frame may wait for the keypoints of remote places (one deadline for
        all the robots it asks).
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
    """One robot's places: a scorer of their words, the place id <-> frame tables, their frames in
    order of arrival (oldest first), the latest frame it offered (-1: none; a catch-up asks for the
    ones after it), the map epoch they belong to, its counters and its recent fetch latencies (ms)."""

    def __init__(self, scorer: Scorer, epoch: int) -> None:
        self.scorer = scorer
        self.epoch = epoch
        self.frame_of: dict[int, int] = {}
        self.place_of: dict[int, int] = {}
        self.arrivals: deque[int] = deque()
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
        self._cache: OrderedDict[tuple[str, int], PlaceKeypoints] = OrderedDict()
        self.evicted = 0
        #: Refusals of messages from robots the map does not hold (unreadable, other bundle, one
        #: robot too many), by reason: per-robot counters would let a peer grow them without bound.
        self.refused_elsewhere: dict[str, int] = {}
        #: Robots whose map epoch changed since the caller last emptied this list.
        self.restarted: list[str] = []
        #: Robots a summary of another epoch was sent in the name of, for the caller to ask (then empty it).
        self.epoch_claims: set[str] = set()
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

    def add(self, summary: PlaceSummary, alive: Callable[[str], bool] = lambda robot: True) -> bool:
        """Keep a remote place; False (counted under a reason) when it is refused.

        alive(robot): whether the node sees that robot's liveliness token now. A robot not held is
        admitted only when alive; when max_robots are held, one whose token is gone is dropped
        to make room. A summary of another epoch than the robot's held one changes nothing (see
        the module doc: `epoch_claims`, `confirm_epoch`)."""
        if summary.robot == self.config.robot:
            return False  # our own summaries, back through a router: not a remote place
        robot = self.robots.get(summary.robot)
        if robot is None:
            if not alive(summary.robot):
                self.refuse(summary.robot, "not_alive")
                return False
            if len(self.robots) >= self.config.max_robots and not self._drop_gone_robot(alive):
                self.refuse(summary.robot, "too_many_robots")
                return False
            robot = self.robots[summary.robot] = RemoteRobot(self._make_scorer(), summary.epoch)
        elif summary.epoch != robot.epoch:
            robot.refuse("unconfirmed_epoch")
            self.epoch_claims.add(summary.robot)
            return False
        robot.stats.summaries += 1
        if summary.frame in robot.place_of:
            return False  # held already: a catch-up's replies may overlap what arrived live
        if summary.words.size == 0:
            robot.refuse("no_words")
            return False
        robot.last_frame = max(robot.last_frame, summary.frame)
        pid = robot.scorer.add(summary.words)
        robot.frame_of[pid], robot.place_of[summary.frame] = summary.frame, pid
        robot.arrivals.append(summary.frame)
        self.fit()
        return summary.frame in robot.place_of

    def confirm_epoch(self, name: str, epoch: int) -> bool:
        """What robot `name`'s own session says its map epoch is: a different one than held makes
        the map forget its places (True); the same one changes nothing."""
        robot = self.robots.get(name)
        if robot is None or robot.epoch == epoch:
            return False
        self._forget(name, epoch)
        return True

    def _drop_gone_robot(self, alive: Callable[[str], bool]) -> bool:
        """Drop the first held robot whose token is gone, with its places (room for a live one)."""
        gone = next((name for name in self.robots if not alive(name)), None)
        if gone is None:
            return False
        self._forget(gone, self.robots[gone].epoch, restarted=False)
        del self.robots[gone]
        return True

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
        while self.n_places > limit or (nbytes is not None and self.nbytes() > nbytes):
            if not self._evict_oldest():
                break

    def _forget(self, name: str, epoch: int, restarted: bool = True) -> None:
        """Drop a robot's places and cached keypoints; from now on its places are of `epoch`.
        restarted: it restarted with a new map (counted; the node asks it for all its places)."""
        robot = self.robots[name]
        for pid in robot.frame_of:
            robot.scorer.remove(pid)
        robot.frame_of.clear()
        robot.place_of.clear()
        robot.arrivals.clear()
        for key in [k for k in self._cache if k[0] == name]:
            del self._cache[key]
        robot.epoch, robot.last_frame = epoch, -1
        if self._track is not None and self._track[0] == name:
            self._track = None
        if restarted:
            robot.stats.map_restarts += 1
            self.restarted.append(name)

    def _evict_oldest(self) -> bool:
        """Evict the oldest place of the robot holding the most (False: none holds any); places
        already gone from the scorer are skipped."""
        while True:
            name, robot = max(self.robots.items(), key=lambda item: len(item[1].place_of), default=(None, None))
            if robot is None or not robot.arrivals:
                return False
            frame = robot.arrivals.popleft()
            pid = robot.place_of.pop(frame, None)
            if pid is not None:
                robot.scorer.remove(pid)
                del robot.frame_of[pid]
                self._cache.pop((name, frame), None)
                self.evicted += 1
                return True

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

    def keypoints(self, pairs: Iterable[tuple[str, int]], fetch: Fetch) -> dict[tuple[str, int], PlaceKeypoints]:
        """The keypoints of the (robot, frame) places held: from the cache, the others asked for
        in one `fetch` (kept in the cache when given). Places without keypoints are left out."""
        out: dict[tuple[str, int], PlaceKeypoints] = {}
        wanted = []
        for key in dict.fromkeys(pairs):
            if key in self._cache:
                self._cache.move_to_end(key)
                out[key] = self._cache[key]
            else:
                wanted.append(key)
        got = fetch(wanted) if wanted else {}
        for key in wanted:
            place = got.get(key)
            if place is None:
                continue
            out[key] = place
            robot = self.robots.get(key[0])
            if robot is not None and key[1] in robot.place_of:
                self._cache[key] = place
                while len(self._cache) > self.config.cache_places:
                    self._cache.popitem(last=False)
        if got:
            self.fit()
        return out

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
              fetch: Fetch, max_log10_nfa: float, sequence: int = 0) -> RemoteMatch | None:
        """The most significant verified remote place for query `sequence`, or None.

        checker(bar) -> check(place, bruteforce, retry_only): the own detector's pair check
        (LoopClosureDetector.place_check) with the acceptance bar `bar` (log10 NFA). The tracked
        places (`tracked`) come first, each matched by words and retried all-pairs, and the
        first that passes is taken; else each FAB-MAP candidate is matched by words and each
        robot's best also retried all-pairs, as the own map's reach does. The bar is
        max_log10_nfa - log10(pair checks this frame may make). Every place's keypoints are
        asked for at once (`keypoints`).
        """
        tracked = self.tracked(sequence)
        wanted = [c for c in self.candidates(observed) if c not in tracked]
        if not wanted and not tracked:
            return None
        checks = 2 * len(tracked) + len(wanted) + len({r for r, _ in wanted})
        bar = max_log10_nfa - math.log10(checks)
        check = checker(bar)
        places = self.keypoints(tracked + wanted, fetch)
        for robot, frame in tracked:
            place = places.get((robot, frame))
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
            place = places.get((robot, frame))
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
