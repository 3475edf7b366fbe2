"""A node's part in a fleet over Zenoh (run --fleet NAME --robot ID).

`FleetNode` follows the detector's map as a listener (core/map/map_events.py): for every place
the own map stores it publishes a summary (runtime/aefabmap_runtime/core/fleet/fleet_wire.py) on
``aefabmap/fleet/<fleet>/<robot>/place/<frame>``, and it stops offering a place once the map
evicts it; it answers keypoint queries for the places it offers and a query for all its
summaries (a robot that joins late asks once), and holds a liveliness token. Other robots'
summaries arrive on Zenoh's threads into a bounded inbox; before each frame the node reads them
into a FleetMap (runtime/aefabmap_runtime/core/fleet/fleet_map.py), which the detector holds as
its second candidate source (`LoopClosureDetector.attach_remote`): when the own map verified
nothing the core checks the best remote places, fetching their keypoints through `fetch` (all
of a frame's places asked at once, within one deadline; cached), and builds the frame's result
with the remote match in it. The node only does the I/O: it never processes frames nor edits a
result. Every message from a peer is validated; a bad one is counted under a reason and dropped.

Who speaks for a robot: the Zenoh session holding its liveliness token, whose key names that
session (``.../<robot>/alive/<zid>``; the first live one counts). Keypoint, summaries and epoch
replies are believed only from that session (`Reply.replier_id`). Published summaries carry no
sender Zenoh can vouch for, so one of another map epoch is only a claim: the node asks the
robot's own session for its epoch (``.../epoch``) and forgets the robot's places only when that
session confirms a new one. Authentication itself is TLS with access control on the router: with
deploy/zenoh-fleet-router.json5 a robot's certificate may only publish, answer and hold a token
under its own robot id (docs/fleet.md). Without it, anyone on the router may speak for any robot.

Catch-up: summaries published while two robots could not reach each other are lost to Zenoh.
When a robot's liveliness token appears (again), the next frame asks that robot for its
summaries after the latest frame it offered (``.../summaries?after=N``, answered without
waiting); a robot that joins asks everyone for everything once (`join`).

Bounds: the inbox holds at most INBOX_BYTES of summaries between two frames, each no larger than
the bundle's vocabulary allows; robots are admitted only while their token is alive (a full
table makes room by dropping one whose token is gone); a frame waits for keypoints at most
`fetch_timeout_ms` in all.

Threads: Zenoh's callbacks only append to the inbox and the reply lists, flip liveliness flags,
read `_served` (a dict the frame thread replaces entries of; single dict operations are atomic
in CPython) and bump counters under a lock; the detector and the FleetMap are touched by the
frame thread alone (the listener calls come from it).
"""

from __future__ import annotations

import logging
import re
import statistics
import threading
import time
from collections import deque
from dataclasses import replace

import numpy as np
import zenoh

from aefabmap_runtime.errors import ConfigError, TransportError
from aefabmap_runtime.adapters.state_dir import bundle_id
from aefabmap_runtime.core.fleet.fleet_map import FleetConfig, FleetMap
from aefabmap_runtime.core.fleet.fleet_wire import (
    FleetMessageError,
    TOKEN_PATTERN,
    PlaceSummary,
    decode_epoch,
    decode_keypoints,
    encode_epoch,
    encode_keypoints,
    fleet_key,
    max_summary_bytes,
)
from aefabmap_runtime.core.map.keypoint_store import PlaceKeypoints
from aefabmap_runtime.core.map.map_events import MapListener
from aefabmap_runtime.core.records.messages import FleetStats, RemoteRobotStats

log = logging.getLogger("aefabmap.fleet")

#: Summaries waiting for the frame thread; more are dropped and counted ("too_large_or_inbox_full").
INBOX = 20_000
#: Bytes of summaries waiting for the frame thread; likewise.
INBOX_BYTES = 16 << 20
#: Largest keypoint reply read.
MAX_REPLY_BYTES = 1 << 22
#: A Zenoh session id as a token key names it (hex).
_ZID = re.compile(r"[0-9a-f]{1,32}")
#: How long a robot that joins waits for the others' summaries (s).
JOIN_TIMEOUT_S = 5.0


class FleetNode(MapListener):
    """The detector's part in the fleet (see the module doc); use as a context manager. It
    attaches itself to `detector` (listener, remote candidate source) and detaches on close."""

    def __init__(self, session: zenoh.Session, detector, config: FleetConfig) -> None:
        if detector.map.store is None:
            raise ConfigError("--fleet needs verification: other robots' places are verified before they count")
        self.detector, self.config, self.session = detector, config, session
        self.identity = bytes.fromhex(bundle_id(detector.manifest))
        self.map = FleetMap(config, detector.new_scorer, detector.map.room)
        self._max_summary = max_summary_bytes(detector.map.vocabulary_size)
        # (robot, summary, whether the robot's own session sent it: a reply, not a publication)
        self._inbox: deque[tuple[str, bytes, bool]] = deque()
        self._inbox_bytes = 0
        self._served: dict[int, tuple[bytes, PlaceKeypoints]] = {}  # own frame -> (summary, keypoints)
        self._frame_of_place: dict[int, int] = {}
        # sequence -> stamp (ns) of the frames taken since the node joined, until they enter the map
        self._stamps: dict[int, int] = {}
        self._alive: dict[str, bool] = {}
        self._owner: dict[str, str] = {}  # robot -> the session id (hex) of its live token
        self._epochs: deque[tuple[str, int]] = deque()  # (robot, epoch) its own session answered
        self._epoch_asked: set[str] = set()  # robots whose epoch is being asked
        self._returned: deque[str] = deque()  # robots whose token appeared, to catch up with
        self._ask_all: set[str] = set()  # restarted robots: their catch-up asks for every place
        self._replied: dict[str, list[int]] = {}  # asker -> [keypoint replies, bytes] (Zenoh threads write)
        self.out = FleetStats(fleet=config.name, robot=config.robot)
        self._drops = 0  # summaries too large or beyond the inbox, not yet counted by the frame thread
        self._unreadable = 0  # samples that could not be read, likewise
        self._not_owner = 0  # replies from a session that does not hold the robot's token, likewise
        self._claimed = 0  # tokens for a robot another live session holds, likewise
        # guards what Zenoh threads count and fill: _drops, _unreadable, _not_owner, _claimed, _replied,
        # _inbox_bytes, _epochs
        self._drops_lock = threading.Lock()
        self._handles: list = []
        self._serve_stored()
        try:
            self._declare()
        except zenoh.ZError as exc:
            self.close()
            raise TransportError(f"cannot join fleet {config.name}: {str(exc)[:200]}") from exc
        detector.add_listener(self)
        detector.attach_remote(self.map, self.fetch)

    # ------------------------------------------------------------------ Zenoh side

    def _declare(self) -> None:
        c = self.config
        s = self.session
        self._handles += [
            s.declare_subscriber(fleet_key(c.name, "*", "place", "*"), self._on_summary),
            s.declare_queryable(fleet_key(c.name, c.robot, "keypoints", "*"), self._on_keypoint_query),
            s.declare_queryable(fleet_key(c.name, c.robot, "summaries"), self._on_summaries_query),
            s.declare_queryable(fleet_key(c.name, c.robot, "epoch"), self._on_epoch_query),
            s.liveliness().declare_token(fleet_key(c.name, c.robot, "alive", str(s.zid()))),
            s.liveliness().declare_subscriber(fleet_key(c.name, "*", "alive", "*"), self._on_alive, history=True),
        ]

    def join(self, timeout_s: float = JOIN_TIMEOUT_S) -> int:
        """Ask every robot of the fleet for its summaries once (a late joiner's catch-up); returns
        how many arrived (they are read into the map before the next frame)."""
        n = 0
        try:
            # Who speaks for each robot, first: only its session's replies are read.
            for reply in self.session.liveliness().get(fleet_key(self.config.name, "*", "alive", "*"),
                                                       timeout=timeout_s):
                if reply.ok is not None:
                    self._on_alive(reply.ok)
            # Every reply counts: each robot answers with all its summaries under one key, which the
            # default consolidation would reduce to the last.
            for reply in self.session.get(fleet_key(self.config.name, "*", "summaries"), timeout=timeout_s,
                                          consolidation=zenoh.ConsolidationMode.NONE):
                if reply.ok is not None and self._owned(reply, _robot_of(str(reply.ok.key_expr))):
                    self._take(str(reply.ok.key_expr), reply.ok.payload, owned=True)
                    n += 1
        except zenoh.ZError as exc:
            raise TransportError(f"cannot ask fleet {self.config.name} for its places: {str(exc)[:200]}") from exc
        return n

    def _on_summary(self, sample: zenoh.Sample) -> None:
        self._take_safely(sample)

    def _take_safely(self, sample: zenoh.Sample, owned: bool = False) -> None:
        """`_take` from a Zenoh thread: never raises; a failure is counted as malformed (the
        frame thread moves the count into the map)."""
        try:
            self._take(str(sample.key_expr), sample.payload, owned)
        except Exception:  # noqa: BLE001 - a peer's message must never take the node down
            with self._drops_lock:
                self._unreadable += 1

    def _take(self, key: str, payload: zenoh.ZBytes, owned: bool = False) -> None:
        """Queue a summary for the frame thread, unless it is ours, larger than this bundle's
        summaries can be, or the inbox is full (counted); its bytes are copied only when kept."""
        robot = _robot_of(key)
        if robot == self.config.robot:
            return
        size = len(payload)
        with self._drops_lock:  # several Zenoh threads may take at once
            if size > self._max_summary or len(self._inbox) >= INBOX or self._inbox_bytes + size > INBOX_BYTES:
                self._drops += 1
                return
            self._inbox_bytes += size
            self._inbox.append((robot, payload.to_bytes(), owned))

    def _owned(self, reply: zenoh.Reply, robot: str) -> bool:
        """Whether `reply` comes from the session holding `robot`'s token (else counted)."""
        owner = self._owner.get(robot)
        replier = reply.replier_id
        if owner is not None and replier is not None and str(replier.zid) == owner:
            return True
        with self._drops_lock:
            self._not_owner += 1
        return False

    def _on_keypoint_query(self, query: zenoh.Query) -> None:
        try:
            frame_text = str(query.key_expr).rpartition("/")[2]
            entry = self._served.get(int(frame_text)) if frame_text.isdigit() and len(frame_text) < 19 else None
            if entry is None:
                return  # not ours (any more): the asker times out or gets another robot's reply
            data = encode_keypoints(self.identity, int(frame_text), entry[1], self.detector.map_epoch)
            query.reply(str(query.key_expr), data)
            self.out.keypoint_replies += 1
            self.out.bytes_out += len(data)
            asker = query.parameters.get("robot")
            with self._drops_lock:  # several Zenoh threads may answer at once
                if asker and TOKEN_PATTERN.fullmatch(asker) and (
                        asker in self._replied or len(self._replied) < self.config.max_robots):  # bounded
                    counts = self._replied.setdefault(asker, [0, 0])
                    counts[0] += 1
                    counts[1] += len(data)
        except Exception as exc:  # noqa: BLE001 - a query must never take the node down
            log.debug("keypoint query not answered: %s", str(exc)[:200])

    def _on_summaries_query(self, query: zenoh.Query) -> None:
        try:
            after = _after_frame(query.parameters.get("after"))
            if after is None:
                return  # unreadable: the asker times out
            key = fleet_key(self.config.name, self.config.robot, "summaries")  # a reply's key must match the query
            for frame, (summary, _) in list(self._served.items()):
                if frame > after:
                    query.reply(key, summary)
                    self.out.bytes_out += len(summary)
        except Exception as exc:  # noqa: BLE001
            log.debug("summaries query not answered: %s", str(exc)[:200])

    def _on_epoch_query(self, query: zenoh.Query) -> None:
        try:
            query.reply(str(query.key_expr), encode_epoch(self.identity, self.detector.map_epoch))
        except Exception as exc:  # noqa: BLE001
            log.debug("epoch query not answered: %s", str(exc)[:200])

    def _on_alive(self, sample: zenoh.Sample) -> None:
        """A robot's token came or went. The first live token of a robot names the session that
        speaks for it; another session's token for the same robot is counted and ignored."""
        try:
            parts = str(sample.key_expr).split("/")
            robot, zid = (parts[3], parts[5]) if len(parts) == 6 and parts[4] == "alive" else ("", "")
            if robot == self.config.robot or not TOKEN_PATTERN.fullmatch(robot) or not _ZID.fullmatch(zid):
                return
            owner = self._owner.get(robot)
            if sample.kind != zenoh.SampleKind.PUT:
                if owner == zid:  # the robot's own session left
                    del self._owner[robot]
                    self._alive[robot] = False
                return
            if owner is not None and owner != zid:
                with self._drops_lock:
                    self._claimed += 1
                return
            if robot not in self._alive and len(self._alive) >= self.config.max_robots:
                # As many robots as the map may hold: a robot that left makes room, else the newcomer
                # is not followed (a peer cannot grow this without bound).
                gone = next((r for r, up in list(self._alive.items()) if not up), None)
                if gone is None:
                    return
                del self._alive[gone]
            if not self._alive.get(robot) and len(self._returned) < INBOX:
                self._returned.append(robot)
            self._owner[robot] = zid
            self._alive[robot] = True
        except Exception:  # noqa: BLE001
            pass

    def robots_alive(self) -> list[str]:
        """The other robots of the fleet whose liveliness token this node sees now, sorted."""
        return sorted(r for r, alive in list(self._alive.items()) if alive)

    def catch_up(self) -> list[str]:
        """Ask each robot whose token appeared since the last call for its summaries after the
        latest frame it offered (a robot that restarted with a new map: all of them); the replies
        reach the inbox later (nothing waits). Returns the robots asked."""
        asked: list[str] = []
        while self._returned:
            robot = self._returned.popleft()
            if robot in asked or not TOKEN_PATTERN.fullmatch(robot):  # a key a peer chose
                continue
            # A restarted robot's places from before its new epoch was confirmed were refused, and
            # those taken since may be later ones: ask for all, what is held already is skipped.
            after = -1 if robot in self._ask_all else self.map.last_frame(robot)
            try:
                self.session.get(f"{fleet_key(self.config.name, robot, 'summaries')}?after={after}",
                                 lambda reply, robot=robot: self._on_catch_up_reply(reply, robot),
                                 consolidation=zenoh.ConsolidationMode.NONE, timeout=JOIN_TIMEOUT_S)
            except zenoh.ZError as exc:
                log.debug("catch-up with %s not asked: %s", robot, str(exc)[:200])
                continue
            asked.append(robot)
            self._ask_all.discard(robot)
            log.info("fleet %s: robot %s is reachable; asking for its places after frame %d",
                     self.config.name, robot, after)
        return asked

    def _on_catch_up_reply(self, reply: zenoh.Reply, robot: str) -> None:
        if reply.ok is not None and _robot_of(str(reply.ok.key_expr)) == robot and self._owned(reply, robot):
            self._take_safely(reply.ok, owned=True)

    def check_epochs(self) -> list[str]:
        """Ask each robot that a summary of another map epoch was sent in the name of for its
        epoch, from its own session (nothing waits; one question per robot at a time). Returns
        the robots asked."""
        asked = []
        for robot in sorted(self.map.epoch_claims - self._epoch_asked):
            if robot not in self._owner:
                continue  # nobody speaks for it now: its token's return starts a catch-up
            self._epoch_asked.add(robot)
            try:
                self.session.get(fleet_key(self.config.name, robot, "epoch"),
                                 zenoh.handlers.Callback(lambda reply, robot=robot: self._on_epoch_reply(reply, robot),
                                                         lambda robot=robot: self._epoch_asked.discard(robot)),
                                 consolidation=zenoh.ConsolidationMode.NONE, timeout=JOIN_TIMEOUT_S)
            except zenoh.ZError as exc:
                self._epoch_asked.discard(robot)
                log.debug("epoch of %s not asked: %s", robot, str(exc)[:200])
                continue
            asked.append(robot)
        self.map.epoch_claims.clear()
        return asked

    def _on_epoch_reply(self, reply: zenoh.Reply, robot: str) -> None:
        try:
            if reply.ok is None or not self._owned(reply, robot):
                return
            payload = reply.ok.payload
            epoch = decode_epoch(payload.to_bytes() if len(payload) <= 64 else b"", self.identity)
            with self._drops_lock:
                self._epochs.append((robot, epoch))
        except Exception:  # noqa: BLE001 - a peer's reply must never take the node down
            with self._drops_lock:
                self._unreadable += 1

    def fetch(self, pairs: list[tuple[str, int]]) -> dict[tuple[str, int], PlaceKeypoints | None]:
        """The keypoints of other robots' places, all asked at once and waited for until one
        deadline (`fetch_timeout_ms`); a place whose robot is gone, or that is not answered in
        time by its robot's own session with a valid reply, maps to None. Counted per robot."""
        replies = _Replies()
        out: dict[tuple[str, int], PlaceKeypoints | None] = {}
        t0, issued = time.monotonic(), 0
        timeout_s = self.config.fetch_timeout_ms / 1000
        for robot, frame in pairs:
            out[(robot, frame)] = None
            remote = self.map.robots[robot]
            remote.stats.fetches += 1
            if robot not in self._owner:
                continue
            try:  # ?robot=: the owner counts its replies per asker
                self.session.get(
                    f"{fleet_key(self.config.name, robot, 'keypoints', str(frame))}?robot={self.config.robot}",
                    # Every reply: consolidation would keep one per key, maybe a stranger's over the owner's.
                    replies.handler(self, robot, frame), consolidation=zenoh.ConsolidationMode.NONE, timeout=timeout_s)
                issued += 1
            except zenoh.ZError as exc:
                log.debug("fetch from %s failed: %s", robot, str(exc)[:200])
        replies.wait(issued, t0 + timeout_s)
        store = self.detector.map.store
        for (robot, frame), data, size, ms in replies.take():
            remote = self.map.robots.get(robot)
            if remote is None or out.get((robot, frame), 0) is not None:
                continue  # not asked, or answered already
            remote.stats.bytes_in += size
            if data is None:
                remote.refuse("too_large")
                continue
            try:
                out[(robot, frame)] = decode_keypoints(data, self.identity, frame, store.dtype, store.vocabulary_size,
                                                       store.no_word_code, self.map.epoch(robot))
                remote.fetch_ms.append(ms)
            except FleetMessageError as exc:
                remote.refuse(exc.reason)
        for (robot, _), place in out.items():
            if place is None and robot in self.map.robots:
                self.map.robots[robot].stats.fetch_failures += 1
        return out

    # ------------------------------------------------------------------ frame thread (map events)

    def before_frame(self) -> None:
        """Read the summaries and epochs that arrived into the FleetMap, then ask the robots that
        came back for their places, and those another epoch was claimed for, for their epoch."""
        self._drain()
        if self._returned:  # after the drain: ask for what came after the places just read
            self.catch_up()
        if self.map.epoch_claims:
            self.check_epochs()

    def frame_taken(self, sequence: int, words: np.ndarray, stamp_ns: int, features) -> None:
        self._stamps[sequence] = int(stamp_ns)  # the summary of the place it becomes carries it

    def place_inserted(self, place: int, frame: int, words: np.ndarray, keypoints: PlaceKeypoints | None) -> None:
        """Offer the new place: its summary is published and kept for queries. Frames taken
        before the node joined (a loaded map's queue) are offered after a restart (`_serve_stored`)."""
        for seq in [s for s in self._stamps if s < frame]:
            del self._stamps[seq]
        stamp = self._stamps.pop(frame, None)
        if stamp is None or keypoints is None:
            return
        old = self._frame_of_place.get(place)
        if old is not None:
            self._served.pop(old, None)
        c = self.config
        summary = PlaceSummary(c.robot, self.identity, frame, stamp, np.unique(words[words >= 0]),
                               self.detector.map_epoch).encode()
        self._served[frame] = (summary, keypoints)
        self._frame_of_place[place] = frame
        try:
            self.session.put(fleet_key(c.name, c.robot, "place", str(frame)), summary)
            self.out.summaries_out += 1
            self.out.bytes_out += len(summary)
        except zenoh.ZError as exc:
            log.debug("summary of frame %d not published: %s", frame, str(exc)[:200])

    def place_evicted(self, place: int) -> None:
        self._served.pop(self._frame_of_place.pop(place, -1), None)

    def map_loaded(self) -> None:
        """Another map replaced the own one: offer its places instead."""
        self._served, self._frame_of_place, self._stamps = {}, {}, {}
        self._serve_stored()

    def _drain(self) -> None:
        with self._drops_lock:
            drops, self._drops = self._drops, 0
            unreadable, self._unreadable = self._unreadable, 0
            not_owner, self._not_owner = self._not_owner, 0
            claimed, self._claimed = self._claimed, 0
            epochs, self._epochs = list(self._epochs), deque()
        for reason, n in (("too_large_or_inbox_full", drops), ("malformed", unreadable),
                          ("not_from_owner", not_owner), ("robot_claimed_twice", claimed)):
            if n:
                self.map.refused_elsewhere[reason] = self.map.refused_elsewhere.get(reason, 0) + n
        for robot, epoch in epochs:  # the robots' own sessions answered
            self.map.confirm_epoch(robot, epoch)
        alive = lambda robot: bool(self._alive.get(robot))  # noqa: E731
        while self._inbox:
            robot, data, owned = self._inbox.popleft()
            with self._drops_lock:
                self._inbox_bytes -= len(data)
            try:
                summary = PlaceSummary.decode(data, self.identity, self.detector.map.vocabulary_size)
            except FleetMessageError as exc:
                self.map.refuse(robot, exc.reason)
                continue
            if summary.robot != robot:
                self.map.refuse(robot, "robot_mismatch")
                continue
            if owned:  # a reply of the robot's own session: its epoch is believed
                self.map.confirm_epoch(robot, summary.epoch)
            self.map.add(summary, alive)
            if summary.robot in self.map.robots:
                self.map.robots[summary.robot].stats.bytes_in += len(data)
        while self.map.restarted:  # a robot restarted: the places it numbered before are gone; ask for all
            robot = self.map.restarted.pop()
            log.info("fleet %s: robot %s restarted with a new map; its earlier places are forgotten",
                     self.config.name, robot)
            self._ask_all.add(robot)
            self._returned.append(robot)

    def _serve_stored(self) -> None:
        """Offer the places the own map already holds (a loaded map, --state): a restarted node
        serves them again (their summaries go out to robots that ask for all places; nothing is
        re-published)."""
        own, c = self.detector.map, self.config
        for place, frame in own.places():
            kps = own.keypoints(place)
            if kps is None:
                continue
            words = np.unique(np.asarray(own.place_words(place), np.int64))
            summary = PlaceSummary(c.robot, self.identity, frame, 0, words, own.map_epoch).encode()
            self._served[frame] = (summary, kps)
            self._frame_of_place[place] = frame

    def fleet_stats(self) -> FleetStats:
        """The fleet's counters now (a copy; the stats and status messages carry it)."""
        robots = {}
        for name, remote in self.map.robots.items():
            s = replace(remote.stats, refused=dict(remote.stats.refused), places=remote.scorer.n_alive,
                        alive=self._alive.get(name, True),
                        fetch_ms_p50=round(statistics.median(remote.fetch_ms), 3) if remote.fetch_ms else None)
            robots[name] = s
        for name, (replies, nbytes) in list(self._replied.items()):  # robots that fetch but offer nothing yet
            s = robots.setdefault(name, RemoteRobotStats(places=0, alive=self._alive.get(name, True)))
            s.keypoint_replies, s.bytes_out = replies, nbytes
        return replace(self.out, places_served=len(self._served), remote_places=self.map.n_places,
                       remote_evicted=self.map.evicted, refused_elsewhere=dict(self.map.refused_elsewhere),
                       robots=robots)

    def close(self) -> None:
        """Detach from the detector (no more frames reach the fleet) and leave the fleet."""
        self.detector.remove_listener(self)
        self.detector.detach_remote(self.map)
        for handle in self._handles:
            try:
                handle.undeclare()
            except zenoh.ZError:
                pass
        self._handles = []

    def __enter__(self) -> FleetNode:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()


def join_fleet(session: zenoh.Session, detector, config: FleetConfig) -> FleetNode:
    """A FleetNode that has asked the fleet for its places once, as
    `run` and `replay --fleet` start; closed again when that fails. Logs how many places came."""
    node = FleetNode(session, detector, config)
    try:
        n = node.join()
    except BaseException:
        node.close()
        raise
    log.info("fleet %s: robot %s joined, %d places offered by the others", config.name, config.robot, n)
    return node


class _Replies:
    """The keypoint replies of one frame's fetch, filled by Zenoh threads: only those from the
    session holding the robot's token and no larger than MAX_REPLY_BYTES are copied, and the
    frame thread waits for every query to end, or for its deadline."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._got: list[tuple[tuple[str, int], bytes | None, int, float]] = []  # (place, data, size, ms)
        self._ended = 0
        self._t0 = time.monotonic()

    def handler(self, node: FleetNode, robot: str, frame: int) -> zenoh.handlers.Callback:
        def on_reply(reply: zenoh.Reply) -> None:
            try:
                if reply.ok is None or not node._owned(reply, robot):
                    return
                payload = reply.ok.payload
                size = len(payload)
                data = payload.to_bytes() if size <= MAX_REPLY_BYTES else None  # too large: not copied
                with self._cond:
                    self._got.append(((robot, frame), data, size, (time.monotonic() - self._t0) * 1e3))
                    self._cond.notify_all()
            except Exception:  # noqa: BLE001 - a peer's reply must never take the node down
                pass

        return zenoh.handlers.Callback(on_reply, self._ended_one)

    def _ended_one(self) -> None:
        with self._cond:
            self._ended += 1
            self._cond.notify_all()

    def wait(self, asked: int, deadline: float) -> None:
        """Until every query ended or a reply came for each, or the deadline (monotonic s)."""
        with self._cond:
            while self._ended < asked and len({got[0] for got in self._got}) < asked:
                left = deadline - time.monotonic()
                if left <= 0:
                    return
                self._cond.wait(left)

    def take(self) -> list[tuple[tuple[str, int], bytes | None, int, float]]:
        with self._cond:
            got, self._got = self._got, []
        return got


def _robot_of(key: str) -> str:
    """The robot id of a fleet key (``aefabmap/fleet/<fleet>/<robot>/...``), "" when it has none."""
    parts = key.split("/")
    return parts[3] if len(parts) > 3 else ""


def _after_frame(text: str | None) -> int | None:
    """The ``after`` parameter of a summaries query: -1 when absent, None when unreadable."""
    if text is None or text == "-1":
        return -1
    return int(text) if text.isdigit() and len(text) < 19 else None

