"""Replay: run a detector over the frames of an MCAP log (aefabmap log or ROS 2 bag).

The same per-frame core as the live node (runtime/aefabmap_runtime/adapters/node.py) sees the same frames: the image
payloads logged on ``/camera/image`` (the live run logs the bytes it received; raw frames as
lossless gray PNG) with the same capture stamps, in the same order. So, with the same
bundle and a log written with ``image_every=1``, the deterministic result fields must come
out identical; :func:`compare_results` checks that (``aefabmap replay --check``).
Timings and latencies are never compared.

Playback (:class:`PlaybackConfig`): as fast as possible by default, or at a multiple of the
recorded pace (the gaps between the logged capture stamps), optionally after the first Foxglove
viewer subscribed; a ``threading.Event`` stops a replay between frames.
"""

from __future__ import annotations

import json
import math
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

from aefabmap_runtime.errors import ConfigError
from aefabmap_runtime.adapters.frame_loop import FrameLoop
from aefabmap_runtime.adapters.frame_pipeline import FramePipeline
from aefabmap_runtime.adapters.log_set import LogSet, LogSetReader
from aefabmap_runtime.adapters.mcap_log import (
    McapLogConfig,
    McapLogWriter,
    ReadStatus,
)
from aefabmap_runtime.adapters.replay_stats import ReplayStats
from aefabmap_runtime.adapters.ros_bag import open_replay_source
from aefabmap_runtime.core.features.features import EXTRACTION_VERSION
from aefabmap_runtime.core.records.messages import FleetStats, FrameResult

#: Result fields that vary from run to run (wall-clock timings, transport data); --check
#: compares every other field of the result dicts (FrameResult.to_dict() of the core).
NONDETERMINISTIC_FIELDS = ("timings_ms", "latency_ms", "age_ms", "frame_seq")


@dataclass
class CheckReport:
    """Replayed vs logged results, matched by ``sequence``.

    compared: frames present in both; mismatched: frames with at least one differing field;
    field_counts: field -> frames where it differs; only_in_log / only_in_replay: unmatched
    frames (tail_ignored of them after the end of a truncated log are not held against it);
    mismatches: the first few differences as {sequence, field, logged, replayed}.
    complete: the log held an image for every logged result (image_every == 1).
    remote_loops: logged frames verified to another robot's place (run --fleet): what that robot
    offered is not in the log, so they are left out of the comparison.
    """

    compared: int = 0
    matched: int = 0
    mismatched: int = 0
    only_in_log: int = 0
    only_in_replay: int = 0
    tail_ignored: int = 0
    remote_loops: int = 0
    field_counts: dict[str, int] = field(default_factory=dict)
    mismatches: list[dict] = field(default_factory=list)
    complete: bool = True
    notes: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return (
            self.compared > 0
            and self.mismatched == 0
            and self.only_in_log == 0
            and self.only_in_replay == 0
        )

    def describe(self) -> str:
        head = "check OK" if self.ok else "check FAILED"
        text = (
            f"{head}: {self.compared} frames compared, {self.matched} identical, {self.mismatched} differ"
            f", {self.only_in_log} only in log, {self.only_in_replay} only in replay"
        )
        if self.tail_ignored:
            text += f", {self.tail_ignored} after the truncated end ignored"
        if self.remote_loops:
            text += f", {self.remote_loops} loops to other robots' places not compared"
        if self.field_counts:
            text += "; differing fields: " + ", ".join(f"{k}={v}" for k, v in sorted(self.field_counts.items()))
        for note in self.notes:
            text += f"; {note}"
        return text

    def to_dict(self) -> dict:
        d = asdict(self)
        d["ok"] = self.ok
        return d


def _same(a, b, rtol: float, atol: float) -> bool:
    if isinstance(a, bool) or isinstance(b, bool) or a is None or b is None:
        return a == b
    if isinstance(a, (int, float)) and isinstance(b, (int, float)):
        if isinstance(a, float) or isinstance(b, float):
            if math.isnan(a) and math.isnan(b):
                return True
            return math.isclose(a, b, rel_tol=rtol, abs_tol=atol)
        return a == b
    return a == b


def compare_results(
    logged: list[dict],
    replayed: list[dict],
    *,
    fields: tuple[str, ...] | None = None,
    ignore: tuple[str, ...] = NONDETERMINISTIC_FIELDS,
    rtol: float = 1e-6,
    atol: float = 1e-9,
    max_listed: int = 20,
    truncated: bool = False,
) -> CheckReport:
    """Compare result dicts field by field (floats with rtol/atol), matched by ``sequence``.

    fields: the fields to compare; None = every field present in either dict except
    ``ignore`` (a field missing on one side compares as None, so format drift shows up).

    Dicts without an integer ``sequence`` are matched by position. When ``truncated``, the
    replayed frames after the last logged one (and vice versa) are counted as tail_ignored.
    """

    def keyed(docs: list[dict]) -> dict[int, dict]:
        out: dict[int, dict] = {}
        for i, d in enumerate(docs):
            s = d.get("sequence")
            out[s if isinstance(s, int) and not isinstance(s, bool) else i] = d
        return out

    a, b = keyed(logged), keyed(replayed)
    report = CheckReport()
    common = sorted(set(a) & set(b))
    last_common = common[-1] if common else -1
    for s in sorted(set(a) - set(b)):
        if truncated and s > last_common:
            report.tail_ignored += 1
        else:
            report.only_in_log += 1
    for s in sorted(set(b) - set(a)):
        if truncated and s > last_common:
            report.tail_ignored += 1
        else:
            report.only_in_replay += 1
    for s in common:
        if a[s].get("verified_robot") is not None:
            report.remote_loops += 1
            continue
        names = fields if fields is not None else sorted((set(a[s]) | set(b[s])) - set(ignore))
        differing = [f for f in names if not _same(a[s].get(f), b[s].get(f), rtol, atol)]
        report.compared += 1
        if not differing:
            report.matched += 1
            continue
        report.mismatched += 1
        for f in differing:
            report.field_counts[f] = report.field_counts.get(f, 0) + 1
            if len(report.mismatches) < max_listed:
                report.mismatches.append({"sequence": s, "field": f, "logged": a[s].get(f), "replayed": b[s].get(f)})
    return report


@dataclass(frozen=True)
class PlaybackConfig:
    """How a replay plays its frames.

    rate: multiple of the recorded pace (1: the gaps between the capture stamps; 2: twice as
    fast); 0: as fast as possible. max_gap_s: longest wait (s) for one gap, so a long pause in the
    log (or a run boundary) never stalls the replay. wait_viewer_s: with a live view, wait at most
    this long (s) for the first viewer before the first frame; None: do not wait.
    stats_period_s: with a live view, replay time (s of the logged capture stamps) between two
    stats messages on its /lcd/stats (runtime/aefabmap_runtime/adapters/replay_stats.py; `run`'s
    period).
    """

    rate: float = 0.0
    max_gap_s: float = 3.0
    wait_viewer_s: float | None = None
    stats_period_s: float = 5.0

    def __post_init__(self) -> None:
        if not (isinstance(self.rate, (int, float)) and math.isfinite(self.rate) and self.rate >= 0):
            raise ConfigError(f"replay rate must be a finite number >= 0 (0: as fast as possible), got {self.rate!r}")
        if not (isinstance(self.max_gap_s, (int, float)) and math.isfinite(self.max_gap_s) and self.max_gap_s > 0):
            raise ConfigError(f"longest replay gap must be > 0 s, got {self.max_gap_s!r}")
        wait = self.wait_viewer_s
        if wait is not None and not (isinstance(wait, (int, float)) and math.isfinite(wait) and wait > 0):
            raise ConfigError(f"viewer wait must be a finite number of seconds > 0, got {wait!r}")
        period = self.stats_period_s
        if not (isinstance(period, (int, float)) and math.isfinite(period) and period > 0):
            raise ConfigError(f"stats period must be a finite number of seconds > 0, got {period!r}")


class Pacer:
    """Holds each frame until its recorded time, scaled by 1/rate, has come on a monotonic clock.

    Due times are absolute (the previous due time plus the capped, scaled gap), so the time spent
    processing a frame is not added to the gaps. A replay that falls more than ``max_gap_s``
    behind is re-anchored instead of bursting to catch up. Stamps that go back (a new run of a log
    set) count as no gap.
    """

    def __init__(self, config: PlaybackConfig, stop: threading.Event | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.config, self.clock = config, clock
        self.stop = stop if stop is not None else threading.Event()
        self._due: float | None = None
        self._stamp_ns: int | None = None

    def wait(self, stamp_ns: int) -> bool:
        """Wait for the frame captured at ``stamp_ns`` (ns); False when stopped (before or while waiting)."""
        if self.config.rate <= 0:
            return not self.stop.is_set()
        now = self.clock()
        self._due = self._next_due(stamp_ns, now)
        self._stamp_ns = stamp_ns
        delay = self._due - now
        return not (self.stop.wait(delay) if delay > 0 else self.stop.is_set())

    def _next_due(self, stamp_ns: int, now: float) -> float:
        if self._due is None or self._stamp_ns is None:
            return now
        gap_s = min(max(stamp_ns - self._stamp_ns, 0) / 1e9 / self.config.rate, self.config.max_gap_s)
        return max(self._due + gap_s, now - self.config.max_gap_s)


@dataclass
class ReplaySummary:
    """What a replay did; status says how much of the log was read (truncation)."""

    source: str
    frames_read: int
    frames_processed: int
    bad: dict[str, int]
    loops: int
    duration_s: float
    status: ReadStatus
    out_path: str | None = None
    check: CheckReport | None = None
    stopped: bool = False  # by the stop event, before the end of the log

    @property
    def fps(self) -> float:
        return self.frames_processed / self.duration_s if self.duration_s > 0 else 0.0

    def to_dict(self) -> dict:
        d = asdict(self)
        d["fps"] = self.fps
        if self.check is not None:
            d["check"] = self.check.to_dict()
        return d


class _Restarts:
    """The runs of a log set, replayed from the map each started with (LogSetReader.map_starts).

    A run of `aefabmap run --state` started from the map saved at frame N (or an empty one). The
    replay keeps a copy of its own map when it reaches frame N of an earlier run, and loads it
    when that run starts, so frames an earlier run processed after N (lost from its map by the
    restart) are replayed as they happened and checked; runs are compared one by one.
    """

    def __init__(self, reader, detector) -> None:
        self.detector = detector
        self.notes: list[str] = []
        self.replayed_run: list[int] = []  # run of each replayed result
        # Rebuilding maps needs a detector that saves and loads them (not every FrameProcessor does).
        rebuilds = all(hasattr(detector, a) for a in ("state", "load_state", "next_sequence"))
        self._reader = reader if isinstance(reader, LogSetReader) and rebuilds else None
        self._wanted = {m for m in self._reader.file_map_starts if m} if self._reader is not None else set()
        self._saved: dict[int, object] = {}
        self._empty = self._copy() if self._reader is not None and len(self._reader.paths) > 1 else None
        self._run = 0
        self._last_comparable = None  # the first run that cannot be reproduced (None: all can)

    def _copy(self):
        from aefabmap_runtime.core.records.map_state import MapState

        st = self.detector.state().resolve()
        return MapState(dict(st.arrays), dict(st.scalars))

    def before(self, image) -> None:
        """Called before each image is processed: switch maps at a run's start, keep copies."""
        if self._reader is None:
            return
        if image.run != self._run:
            self._start_run(image.run)
        seq = self.detector.next_sequence
        if seq in self._wanted and seq not in self._saved and image.sequence == seq:
            self._saved[seq] = self._copy()

    def _start_run(self, run: int) -> None:
        self._run = run
        start, here = self._reader.map_starts[run], self.detector.next_sequence
        if start is None or start == here or self._last_comparable is not None:
            if start is None:
                self.notes.append(f"run {run + 1} of the log set does not record the map it started with (a log "
                                  "written before that was recorded): replayed with the map so far")
            return
        if start == 0 and self._empty is not None:
            self.detector.load_state(self._empty)
            self.notes.append(f"run {run + 1} started with an empty map: so was its replay")
        elif start in self._saved:
            self.detector.load_state(self._saved[start])
            self.notes.append(f"run {run + 1} resumed from the map saved at frame {start}, after the run before "
                              f"reached frame {here - 1}: replayed from that map")
        else:
            self._last_comparable = run
            self.notes.append(f"run {run + 1} resumed from a map saved at frame {start} that this log cannot "
                              f"rebuild (its frames are not all in the log): runs from {run + 1} on are not compared")

    def compare(self, reader, replayed: list[FrameResult], *, ignore: tuple[str, ...]) -> CheckReport:
        """compare_results run by run (one run: the whole log), merged."""
        if self._reader is None or len(self._reader.results_by_run) <= 1:
            return compare_results([r.to_dict() for r in reader.results], [r.to_dict() for r in replayed],
                                   ignore=ignore, truncated=reader.status.truncated)
        report = CheckReport()
        stop = self._last_comparable if self._last_comparable is not None else len(self._reader.results_by_run)
        for run, logged in enumerate(self._reader.results_by_run[:stop]):
            mine = [r.to_dict() for r, k in zip(replayed, self.replayed_run, strict=True) if k == run]
            part = compare_results([r.to_dict() for r in logged], mine, ignore=ignore,
                                   truncated=reader.status.truncated)
            for name in ("compared", "matched", "mismatched", "only_in_log", "only_in_replay", "tail_ignored",
                         "remote_loops"):
                setattr(report, name, getattr(report, name) + getattr(part, name))
            for f, n in part.field_counts.items():
                report.field_counts[f] = report.field_counts.get(f, 0) + n
            report.mismatches += part.mismatches[: max(0, 20 - len(report.mismatches))]
        return report


def replay(
    detector,
    mcap_path: str | Path | list[str | Path],
    *,
    out_path: str | Path | None = None,
    check: bool = False,
    image_topic: str | None = None,
    log_config: McapLogConfig | None = None,
    on_result: Callable[[dict], None] | None = None,
    view=None,
    playback: PlaybackConfig | None = None,
    stop: threading.Event | None = None,
    workers: int = 1,
    fleet_stats: Callable[[], FleetStats] | None = None,
) -> ReplaySummary:
    """Run ``detector`` (see frame_loop.FrameProcessor) over the images of ``mcap_path``: an aefabmap
    log, or a ROS bag (directory, .db3, .mcap, ROS 1 .bag; runtime/aefabmap_runtime/adapters/ros_bag.py).

    mcap_path: one log, or a log set read in run order as one run: a directory of rotated
    files, a glob, or a list of those (runtime/aefabmap_runtime/adapters/log_set.py).

    out_path: write a new log (images, replayed results, final stats, manifest metadata).
    check: compare the replayed results with the ones logged (all but NONDETERMINISTIC_FIELDS,
    and fields added to the message format after the log's version).
    image_topic: which image topic to read (default: the log's image topic, else the first found).
    on_result: called with each replayed result's dict.
    view: a foxglove_view.LiveView shown every replayed frame (its log is set to ``out_path``'s),
    with `run`'s stats messages every ``playback.stats_period_s`` of replay time and at the end
    (runtime/aefabmap_runtime/adapters/replay_stats.py); fleet_stats: the fleet counters they carry.
    playback: pace and viewer wait (default: as fast as possible, no wait). stop: set it to end
    the replay between frames (or the viewer wait); the summary then says ``stopped``.
    workers: threads that work on frames (runtime/aefabmap_runtime/adapters/frame_pipeline.py;
    the same results).
    Raises LogError when the source cannot be read (or is of a newer format) or the output
    not written, ConfigError when waiting for a viewer without a view, TransportError when none
    came in time.
    """
    playback = playback or PlaybackConfig()
    stop = stop if stop is not None else threading.Event()
    reader = open_replay_source(mcap_path, image_topic=image_topic)
    if playback.wait_viewer_s is not None:
        if view is None:
            raise ConfigError("waiting for a viewer needs the Foxglove live view")
        view.wait_viewer(playback.wait_viewer_s, stop)  # a stop here ends the replay at its first frame
    pacer = Pacer(playback, stop)
    stopped = False
    source = str(mcap_path) if isinstance(mcap_path, (str, Path)) else ", ".join(map(str, mcap_path))
    replayed: list[FrameResult] = []
    loop = FrameLoop(detector)
    restarts = _Restarts(reader, detector)
    writer = None
    t0 = time.monotonic()
    manifest = getattr(detector, "manifest", None)
    if out_path is not None:
        # Like `run`, never overwrite: an existing NEW.mcap gets NEW-0001.mcap beside it; a
        # missing DIR/ is created.
        out_set = LogSet(out_path)
        out_set.make_directory()
        out_path, writer = out_set.create_next(lambda path, opened_ns: McapLogWriter(
            path,
            log_config or McapLogConfig(),
            manifest=manifest if isinstance(manifest, dict) else None,
            run_config={"replay_of": source, "image_topic": image_topic, "started_ns": time.time_ns()},
            exclusive=True,
        ))
    if view is not None and writer is not None:
        view.attach_log(writer)
    stats = None if view is None else ReplayStats(
        loop, playback.stats_period_s, lambda _msg, data, stamp_ns: view.on_stats(data, stamp_ns), fleet_stats)

    def decided(image, out) -> None:
        if stats is not None:
            stats.decided(image.stamp_ns, out.result is not None)
        if out.result is None:
            return  # counted by the frame loop
        result = out.result
        replayed.append(result)
        restarts.replayed_run.append(getattr(image, "run", 0))
        if on_result is not None:
            on_result(result.to_dict())
        if writer is not None:
            writer.write_image(image.payload, image.encoding, image.stamp_ns, sequence=result.sequence,
                               gray=out.gray)
        if view is not None:
            view.on_frame(image.payload, image.encoding, out.gray, result)
        if writer is not None:
            writer.write_result(result)

    try:
        # Frames in flight: decoded and extracted ahead, decided in order (restarts switch maps just before).
        with FramePipeline(loop, workers, before=restarts.before) as pipe:
            for image in reader.frames():
                if not pacer.wait(image.stamp_ns):
                    stopped = True
                    break
                if stats is not None:
                    stats.started()
                pipe.put_payload(image, image.payload, image.encoding, image.stamp_ns)
                while pipe.full:
                    decided(*pipe.take())
            while pipe.pending and not stopped:
                decided(*pipe.take())
        if stats is not None:
            stats.final()
        duration = time.monotonic() - t0
        if writer is not None:
            writer.write_stats(loop.stats_message(uptime_s=duration, fps=round(loop.processed / duration, 2)
                                                  if duration > 0 else None))
    finally:
        if writer is not None:
            writer.close()
    report = None
    if check:
        version = reader.format_version
        newer = FrameResult.fields_since(version) if version is not None else ()
        report = restarts.compare(reader, replayed, ignore=NONDETERMINISTIC_FIELDS + newer)
        if newer:
            report.notes.append(f"not in this log's format {reader.status.format_version}, not compared: "
                                + ", ".join(newer))
        if reader.status.invalid_messages:
            report.notes.append(f"{reader.status.invalid_messages} logged messages failed validation "
                                f"(last: {reader.status.last_invalid})")
        if not reader.results:
            report.notes.append("the log holds no /lcd/result messages to compare with")
        if reader.results and reader.status.images_read < len(reader.results):
            report.complete = False
            report.notes.append(
                f"the log has {reader.status.images_read} images for {len(reader.results)} results "
                "(logged with image_every > 1?): the replayed detector saw fewer frames, so results differ"
            )
        logged_manifest = reader.manifest
        if (
            logged_manifest is not None
            and isinstance(manifest, dict)
            and logged_manifest != json.loads(json.dumps(manifest, sort_keys=True, default=str))
        ):
            report.notes.append("the bundle manifest differs from the one in the log")
        report.notes += _extraction_notes(reader, report)
        if stopped:
            report.notes.append(f"the replay was stopped after {loop.frames_in} frames")
        if reader.status.truncated:
            report.notes.append("the log was truncated (no summary): compared up to its last complete chunk")
        if reader.results and reader.results[0].sequence > 0:
            report.notes.append(f"the log starts at frame {reader.results[0].sequence} (its first files deleted by "
                                "the log budget?): the replay starts with an empty map, so results differ")
        report.notes += restarts.notes
    return ReplaySummary(
        source=source,
        frames_read=loop.frames_in,
        frames_processed=loop.processed,
        bad=dict(loop.bad.counts),
        loops=loop.loops,
        duration_s=time.monotonic() - t0,
        status=reader.status,
        out_path=str(out_path) if out_path is not None else None,
        check=report,
        stopped=stopped,
    )


def _extraction_notes(reader, report: CheckReport) -> list[str]:
    """Why a check may differ on the features: the log names another extraction version than
    this build's, or (with differences found) an aefabmap log that names none."""
    logged = reader.extraction_version
    if logged is not None and logged != EXTRACTION_VERSION:
        note = (f"the log was written by a build that extracts features otherwise (extraction version {logged}, "
                f"this build {EXTRACTION_VERSION}; CHANGELOG.md): keypoints, and what follows, may differ")
        return [note]
    if logged is None and report.mismatched and reader.format_version is not None:
        note = ("the log does not record its feature extraction version (written before aefabmap recorded it): "
                f"a build before extraction version {EXTRACTION_VERSION} (CHANGELOG.md) gives other keypoints on "
                "frames resized for detection")
        return [note]
    return []
