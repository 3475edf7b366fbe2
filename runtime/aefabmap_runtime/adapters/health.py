"""A running node's health on Zenoh: a liveliness token and a status queryable.

Keys (one pair per node, ``<zid>`` being the Zenoh id of its session):

- liveliness token ``aefabmap/runtime/<zid>``: present while the node runs, gone when it stops
  (or its session dies), so ``zenoh liveliness get aefabmap/runtime/*`` lists the live nodes;
- queryable ``aefabmap/status/<zid>``: answers any query with one StatusMessage
  (runtime/aefabmap_runtime/core/records/messages.py) in JSON. Query parameters and payload are ignored (untrusted).

Threads: the frame loop copies its counters into a :class:`StatusBoard` after each frame
(under a lock held for a few dict copies); a query is answered on a Zenoh thread from that
copy, so it never waits for a frame and never touches the detector. An answer is reused for
ANSWER_REUSE_S (a query flood builds at most one status per period). A query that cannot be
answered is counted (``HealthEndpoint.errors``), never raised into Zenoh.
"""

from __future__ import annotations

import os
import statistics
import threading
import time
from collections import deque
from collections.abc import Callable

import zenoh

from aefabmap_runtime.version import __version__
from aefabmap_runtime.errors import InputError, TransportError
from aefabmap_runtime.adapters.state_dir import bundle_id
from aefabmap_runtime.core.records.messages import MESSAGE_FORMAT_VERSION, FleetStats, StatusMessage

__all__ = ["RUNTIME_TOKEN_PREFIX", "STATUS_PREFIX", "HealthEndpoint", "StatusBoard", "find_runtimes",
           "query_status", "rss_mb", "status_key", "token_key", "wait_for_peer"]

RUNTIME_TOKEN_PREFIX = "aefabmap/runtime"
STATUS_PREFIX = "aefabmap/status"
#: Frames whose timings_ms make the per-stage medians of a status.
RECENT_FRAMES = 100
#: An answer is reused for this long (s): a flood of queries costs at most one status build per
#: period (a small fraction of a frame's CPU; docs/results.md, "Streaming"), so it cannot starve
#: the frame loop.
ANSWER_REUSE_S = 0.05


def token_key(zid: str) -> str:
    return f"{RUNTIME_TOKEN_PREFIX}/{zid}"


def status_key(zid: str) -> str:
    return f"{STATUS_PREFIX}/{zid}"


def rss_mb() -> float | None:
    """Resident set size of this process in MB (from /proc/self/statm; None elsewhere)."""
    try:
        with open("/proc/self/statm", "rb") as f:
            pages = int(f.read().split()[1])
        return pages * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (OSError, ValueError, IndexError):
        return None


def peak_rss_mb() -> float | None:
    """Largest resident set size this process has had, in MB, as the kernel kept it (VmHWM of
    /proc/self/status, else getrusage's ru_maxrss); None where neither is available. Sampling
    rss_mb() misses peaks between samples."""
    try:
        with open("/proc/self/status", "rb") as f:
            for line in f:
                if line.startswith(b"VmHWM:"):
                    return int(line.split()[1]) / 1024  # kB
    except (OSError, ValueError, IndexError):
        pass
    try:
        import resource

        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # kB on Linux
    except (ImportError, OSError):
        return None


def _log_usage(log) -> tuple[int, int]:
    """(files still on disk, their bytes) of a RotatingLog's run; stat only, no lock needed."""
    files, size = 0, 0
    for path in list(getattr(log, "files", ())):
        try:
            size += os.stat(path).st_size
            files += 1
        except OSError:  # deleted by the budget meanwhile
            continue
    return files, size


class StatusBoard:
    """The node's counters as the status queryable sees them (thread-safe copy).

    after_frame() runs on the frame thread; status() on any thread.
    """

    def __init__(self, *, image_key: str, results_key: str, manifest: dict | None, log=None,
                 t0: float | None = None, recent: int = RECENT_FRAMES) -> None:
        self.image_key, self.results_key, self.log = image_key, results_key, log
        self.bundle_id = bundle_id(manifest) if isinstance(manifest, dict) else None
        self.t0 = time.monotonic() if t0 is None else t0
        self._lock = threading.Lock()
        self._timings: deque[dict] = deque(maxlen=recent)
        self._counters: dict = {"frames_received": 0, "frames_processed": 0, "dropped": 0, "bad": {}, "loops": 0}
        self._places: int | None = None
        self._map_mb: float | None = None
        self._fleet = None
        #: Returns the node's current warnings (StatusMessage.warnings); set by the node.
        self.warnings: Callable[[], list[str]] | None = None
        #: Returns the fleet's counters (FleetNode.fleet_stats); set by a node in a fleet.
        self.fleet_stats: Callable[[], FleetStats] | None = None
        #: Whether a ROS 2 run's image topic is published (ros_topic_check.ImageTopicCheck); set by the node.
        self.topic_check = None

    def after_frame(self, loop, drops, result=None, detector=None) -> None:
        """Copy the frame loop's counters (and the result's timings, the map's size)."""
        counters = {"frames_received": loop.frames_in, "frames_processed": loop.processed,
                    "dropped": getattr(drops, "dropped", 0), "bad": dict(loop.bad.counts), "loops": loop.loops}
        map_bytes = getattr(detector, "map_bytes", None)
        map_mb = None
        if callable(map_bytes):
            try:
                map_mb = round(map_bytes() / 2**20, 3)
            except Exception:  # a detector without a sizable map: not told  # noqa: BLE001
                map_mb = None
        fleet = self.fleet_stats() if self.fleet_stats is not None else None
        with self._lock:
            self._counters = counters
            self._fleet = fleet
            if result is not None:
                self._timings.append(dict(result.timings_ms))
                self._places = result.n_places
            if map_mb is not None:
                self._map_mb = map_mb

    def status(self, zid: str) -> StatusMessage:
        with self._lock:
            counters, timings = self._counters, list(self._timings)
            places, map_mb, fleet = self._places, self._map_mb, self._fleet
        stages: dict[str, list[float]] = {}
        for t in timings:
            for name, ms in t.items():
                stages.setdefault(name, []).append(float(ms))
        rss = rss_mb()
        files, size = _log_usage(self.log)
        return StatusMessage(
            stamp_ns=time.time_ns(), zid=zid, aefabmap_version=__version__,
            message_format_version=MESSAGE_FORMAT_VERSION, bundle_id=self.bundle_id,
            uptime_s=round(time.monotonic() - self.t0, 3), image_key=self.image_key, results_key=self.results_key,
            places=places, map_mb=map_mb, rss_mb=None if rss is None else round(rss, 1),
            stage_ms={k: round(statistics.median(v), 3) for k, v in stages.items()}, recent_frames=len(timings),
            log_files=files, log_bytes=size, log_errors=getattr(self.log, "errors", 0),
            log_state=getattr(self.log, "state", None), warnings=self._current_warnings(), fleet=fleet,
            **self._ros_topic(), **counters,
        )

    def _ros_topic(self) -> dict:
        """The status's ros_topic_published / ros_image_topics (nothing outside a ROS 2 run)."""
        check = self.topic_check
        if check is None:
            return {}
        try:
            published = check.published()
            return {"ros_topic_published": published,
                    "ros_image_topics": check.image_topics() if published is False else []}
        except Exception:  # noqa: BLE001 - a status is answered even when the graph cannot be read
            return {}

    def _current_warnings(self) -> list[str]:
        try:
            return list(self.warnings()) if self.warnings is not None else []
        except Exception:  # noqa: BLE001 - a status is answered even when its warnings cannot be listed
            return ["warnings unavailable"]


class HealthEndpoint:
    """Declares the liveliness token and the status queryable of a node on ``session``."""

    def __init__(self, session: zenoh.Session, board: StatusBoard) -> None:
        self.zid = str(session.zid())
        self.board = board
        self.answered = 0
        self.errors = 0
        self.last_error = ""
        self._token = None
        self._queryable = None
        self._answer_lock = threading.Lock()
        self._answer: tuple[float, bytes] = (-1e9, b"")
        try:
            self._queryable = session.declare_queryable(status_key(self.zid), self._on_query)
            self._token = session.liveliness().declare_token(token_key(self.zid))
        except zenoh.ZError as exc:
            self.close()
            raise TransportError(f"cannot declare the status of {self.zid}: {str(exc)[:200]}") from exc

    def _on_query(self, query: zenoh.Query) -> None:
        # Runs on a Zenoh thread: never raise (parameters and payload are not even read).
        try:
            data = self._current_answer()
            query.reply(status_key(self.zid), data, encoding=zenoh.Encoding.APPLICATION_JSON)
            self.answered += 1
        except Exception as exc:  # noqa: BLE001 - a status query must never take the node down
            self.errors += 1
            self.last_error = str(exc)[:200]

    def _current_answer(self) -> bytes:
        with self._answer_lock:  # queries may arrive on several Zenoh threads at once
            made, data = self._answer
            now = time.monotonic()
            if now - made >= ANSWER_REUSE_S:
                data = self.board.status(self.zid).to_json_bytes()
                self._answer = (now, data)
            return data

    def close(self) -> None:
        for handle in (self._token, self._queryable):
            if handle is not None:
                try:
                    handle.undeclare()
                except zenoh.ZError:
                    pass
        self._token = self._queryable = None


# ----------------------------------------------------------------------------- client side


def wait_for_peer(session: zenoh.Session, timeout_s: float) -> bool:
    """True once the session is connected to some peer or router (within timeout_s)."""
    deadline = time.monotonic() + timeout_s
    pause = threading.Event()
    while True:
        info = session.info
        if list(info.peers_zid()) or list(info.routers_zid()):
            return True
        if time.monotonic() >= deadline:
            return False
        pause.wait(0.01)  # the connection is made by Zenoh's own threads: poll its state


def find_runtimes(session: zenoh.Session, timeout_s: float) -> list[str]:
    """Zenoh ids of the nodes whose liveliness token is visible, sorted."""
    zids = set()
    try:
        replies = session.liveliness().get(f"{RUNTIME_TOKEN_PREFIX}/*", timeout=timeout_s)
        for reply in replies:
            if reply.ok is not None:
                zids.add(str(reply.ok.key_expr).rpartition("/")[2])
    except zenoh.ZError as exc:
        raise TransportError(f"cannot list aefabmap runtimes: {str(exc)[:200]}") from exc
    return sorted(zids)


def query_status(session: zenoh.Session, zids: list[str], timeout_s: float) -> dict[str, StatusMessage | str]:
    """Each node's StatusMessage, or a one-line reason when it gave none (queried in parallel)."""
    pending = {}
    try:
        for zid in zids:
            pending[zid] = session.get(status_key(zid), timeout=timeout_s)
        out: dict[str, StatusMessage | str] = {}
        for zid, replies in pending.items():
            out[zid] = "no answer"
            for reply in replies:
                if reply.ok is None:
                    out[zid] = f"error reply: {str(reply.err.payload.to_string())[:120]}"
                    continue
                try:
                    out[zid] = StatusMessage.from_json(reply.ok.payload.to_bytes())
                except InputError as exc:
                    out[zid] = str(exc)
                break
    except zenoh.ZError as exc:
        raise TransportError(f"cannot query aefabmap runtimes: {str(exc)[:200]}") from exc
    return out
