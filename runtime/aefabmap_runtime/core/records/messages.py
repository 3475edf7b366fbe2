"""The wire messages of the runtime: one typed record per message, its JSON and its schema.

Every message that leaves a process (Zenoh results and stats, MCAP log, the `aefabmap run`
summary line) is one of these dataclasses. From the fields come:

- ``to_dict()`` / ``to_json_bytes()``: the JSON text, serialised once per message and used
  for both the Zenoh publication and the MCAP record;
- ``json_schema()``: the JSON schema the MCAP writer stores for the channel, generated from
  the type hints (runtime/aefabmap_runtime/core/records/json_schema.py), so schema and message cannot drift;
- ``from_json()``: the parser every reader uses; it validates against that schema and
  raises InputError (one line) for a malformed message. Unknown keys are ignored (a newer
  minor format may add fields); missing optional ones take their defaults.

``MESSAGE_FORMAT_VERSION`` is "major.minor": a minor version only adds optional fields (the
field metadata ``since`` says which), so a reader reads every log of its major version and
refuses a newer major one. JSON keys are kept stable across versions: old logs compare.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from typing import Any, Self

from aefabmap_runtime.errors import InputError
from aefabmap_runtime.core.records.json_schema import schema_for_dataclass, validate

#: Format of the messages (and of the log layout that carries them): "major.minor".
#: 1.0: the first logs ("1"); 1.1: generated schemas, ``score_kind``; 1.2: the log's health in
#: the stats (``log_errors``, ``log_state``) and the run summary (``log_files``...); 1.3: ``nfa``,
#: ``geometry_reason``, ``candidates``; 1.4: ``relative_rotation``, ``relative_translation``;
#: 1.5: ``sequence_nfa``, the status's ``warnings``; 1.6: ``verified_robot``, ``fleet``; 1.7: the
#: fleet's per-robot ``map_restarts``, ``keypoint_replies`` and ``bytes_out``; 1.8: the status's
#: ``ros_topic_published`` and ``ros_image_topics``.
MESSAGE_FORMAT_VERSION = "1.8"

#: Values of StatsMessage.log_state (runtime/aefabmap_runtime/adapters/rotating_log.py).
LOG_STATES = ("ok", "images_stopped", "stopped", "failed", "closed")

#: What ``score`` of a result holds: see FrameResult.score_kind.
SCORE_KINDS = ("probability", "llr", "similarity")

#: Result fields added by the transport (the live node), absent from replayed results.
TRANSPORT_FIELDS = ("frame_seq", "latency_ms", "age_ms")


def _meta(description: str, *, enum: tuple | None = None, since: str | None = None) -> dict[str, Any]:
    """Schema metadata of a field: description, allowed values, format version that added it."""
    meta: dict[str, Any] = {"description": description} if description else {}
    if enum is not None:
        meta["enum"] = enum
    if since is not None:
        meta["since"] = since
    return meta


def _f(default: Any = dataclasses.MISSING, description: str = "", *, enum: tuple | None = None,
       since: str | None = None, init: bool = True) -> Any:
    """A dataclass field of an immutable value with its schema metadata (see _meta)."""
    return field(default=default, init=init, metadata=_meta(description, enum=enum, since=since))


def parse_version(text: Any) -> tuple[int, int]:
    """(major, minor) of a "major[.minor]" version string; raises InputError when malformed."""
    parts = str(text).strip().split(".")
    if not 1 <= len(parts) <= 2 or not all(p.isdigit() for p in parts):
        raise InputError(f"malformed message format version {str(text)[:40]!r}")
    return int(parts[0]), int(parts[1]) if len(parts) == 2 else 0


def check_readable(text: Any) -> tuple[int, int]:
    """The parsed version of a log/message format, if this code reads it; else InputError."""
    version = parse_version(text)
    ours = parse_version(MESSAGE_FORMAT_VERSION)
    if version[0] > ours[0]:
        raise InputError(
            f"message format {text} is newer than this aefabmap reads ({ours[0]}.x): upgrade aefabmap"
        )
    return version


_SCHEMAS: dict[type, dict] = {}


class _Message:
    """JSON, schema and validating parser of a message dataclass (see the module docstring)."""

    TITLE = ""
    DESCRIPTION = ""

    @classmethod
    def json_schema(cls) -> dict:
        """The channel's JSON schema, generated from the fields (a fresh copy)."""
        if cls not in _SCHEMAS:
            _SCHEMAS[cls] = schema_for_dataclass(cls, title=cls.TITLE, description=cls.DESCRIPTION)
        return json.loads(json.dumps(_SCHEMAS[cls]))

    @classmethod
    def fields_since(cls, version: tuple[int, int]) -> tuple[str, ...]:
        """Fields added after format ``version`` (a log of that version cannot hold them)."""
        return tuple(f.name for f in dataclasses.fields(cls)
                     if "since" in f.metadata and parse_version(f.metadata["since"]) > version)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def to_json_bytes(self) -> bytes:
        """Compact UTF-8 JSON (NaN allowed, as Python writes it): the bytes sent and logged."""
        return json.dumps(self.to_dict(), separators=(",", ":"), allow_nan=True).encode()

    @classmethod
    def from_json(cls, data: bytes | bytearray | memoryview | str | dict) -> Self:
        """Parse and validate one message (JSON text/bytes or an already decoded dict)."""
        if isinstance(data, dict):
            doc = data
        else:
            try:
                doc = json.loads(bytes(data) if isinstance(data, memoryview) else data)
            except (ValueError, UnicodeDecodeError) as exc:
                raise InputError(f"{cls.TITLE} message is not JSON: {str(exc)[:80]}") from exc
        schema = _SCHEMAS.get(cls) or cls.json_schema()
        if (err := validate(doc, schema)) is not None:
            raise InputError(f"{cls.TITLE} message: {err}"[:300])
        return _build(cls, doc)


def _build(cls: type, doc: dict) -> Any:
    """A dataclass from a validated dict: known init fields only, floats as float."""
    hints = _hints(cls)
    kwargs = {f.name: _coerce(hints[f.name], doc[f.name]) for f in dataclasses.fields(cls)
              if f.init and f.name in doc}
    return cls(**kwargs)


_HINTS: dict[type, dict] = {}


def _hints(cls: type) -> dict:
    if cls not in _HINTS:
        import typing

        _HINTS[cls] = typing.get_type_hints(cls)
    return _HINTS[cls]


def _coerce(hint: Any, value: Any) -> Any:
    import typing

    if value is None:
        return None
    args = typing.get_args(hint)
    origin = typing.get_origin(hint)
    if args and type(None) in args:  # X | None
        return _coerce(next(a for a in args if a is not type(None)), value)
    if hint is float:
        return float(value)
    if origin is dict:
        return {k: _coerce(args[1], v) for k, v in value.items()}
    if origin is list:
        return [_coerce(args[0], v) for v in value]
    if dataclasses.is_dataclass(hint):
        return _build(hint, value)
    return value


# ============================================================================ results


@dataclass
class Candidate:
    """One place the detector considered for a frame (evidence for evaluation and logs)."""

    place: int = _f(description="place id")
    frame: int = _f(description="sequence of the frame that made the place")
    rank: int = _f(description="0-based position in the FAB-MAP log-likelihood (or BoW similarity) ranking")
    probability: float | None = _f(None, "FAB-MAP posterior (null with BoW)")
    llr: float | None = _f(None, "log-likelihood ratio against the new place, nats (null with BoW)")
    similarity: float | None = _f(None, "BoW cosine similarity (null with FAB-MAP)")
    checked: bool = _f(False, "geometrically verified this frame")
    source: str | None = _f(None, "why it was checked: track, fabmap or island (null: not checked)")
    verified: bool = _f(False, "its geometric check passed")
    inliers: int = _f(0, "inliers of its check")
    matches: int = _f(0, "putative matches of its check")
    model: str | None = _f(None, "geometry model of its check", enum=("F", "E", "H"))
    nfa: float | None = _f(None, "log10 number of false alarms of its check (null: no model fitted)")
    inlier_points: list[list[float]] | None = _f(None, (
        "inlier pairs [x_q, y_q, x_p, y_p], original pixels; only with VerificationConfig.keep_inlier_points "
        "(evaluation), null otherwise"))


@dataclass
class FrameResult(_Message):
    """What the detector says about one frame (+ the transport fields of a live run).

    The per-field descriptions are the schema's; see runtime/aefabmap_runtime/core/detector.py for how the
    detector fills them.
    """

    TITLE = "aefabmap.LcdResult"
    DESCRIPTION = ("loop-closure result of one frame: the detector's record, plus frame_seq, latency_ms "
                   "and age_ms on live runs")

    sequence: int = _f(description="0-based index of the processed frame in the stream")
    stamp_ns: int = _f(description="capture time of the frame, ns since the Unix epoch")
    n_keypoints: int = _f(description="keypoints extracted")
    n_words: int = _f(description="distinct visual words among them")
    best_place: int | None = _f(description="best candidate place id (null: the map is empty)")
    best_frame: int | None = _f(description="sequence of the frame that made best_place")
    score: float = _f(description=(
        "score of best_place; what it holds is named by score_kind: the FAB-MAP posterior P "
        "('probability'), the log-likelihood ratio against the new-place model in nats ('llr'; "
        "DetectorConfig.fabmap_score), or the BoW cosine similarity ('similarity'); 0 when the map is empty"))
    p_new: float | None = _f(description="FAB-MAP new-place probability (null with the BoW scorer)")
    loop: bool = _f(description="loop closure accepted: verified (verification on) or score >= loop_threshold")
    probability: float | None = _f(None, "FAB-MAP posterior P of best_place")
    llr: float | None = _f(None, "log-likelihood ratio of best_place against the new place, nats")
    inserted_frame: int | None = _f(None, "frame that entered the map during this step (delayed insertion)")
    inserted_place: int | None = _f(None, "place id of inserted_frame")
    evicted_place: int | None = _f(None, "place evicted to respect max_places / memory_mb")
    n_places: int = _f(0, "places in the map after this step")
    timings_ms: dict[str, float] = field(default_factory=dict, metadata=_meta("detector time per stage, ms"))
    verified: bool = _f(False, "a candidate passed geometric (+ temporal) verification")
    verified_place: int | None = _f(None, "place id of the verified candidate")
    verified_frame: int | None = _f(None, "sequence of the frame that made verified_place")
    inliers: int = _f(0, "inliers of the accepted geometry (or of the best attempt)")
    matches: int = _f(0, "putative keypoint matches behind inliers")
    geometry_model: str | None = _f(None, "F: fundamental matrix, E: essential matrix (calibrated camera), H: homography",
                                    enum=("F", "E", "H"))
    geometry: list[list[float]] | None = field(default=None, metadata=_meta(
        "3x3 row-major matrix mapping the place image to the query image, original pixels; null unless verified"))
    relative_rotation: list[list[float]] | None = field(default=None, metadata=_meta(
        "verified with an essential matrix (calibrated camera, geometry_model E) only, else null: 3x3 row-major "
        "rotation R_pq of the QUERY camera relative to the matched PLACE camera (columns: the query camera's axes "
        "in place-camera coordinates; X_place = R_pq X_query + t_pq)", since="1.4"))
    relative_translation: list[float] | None = _f(None, (
        "with relative_rotation: direction of t_pq, the query camera's centre in place-camera coordinates, unit "
        "length (two views give no scale); null otherwise"), since="1.4")
    candidates_tried: int = _f(0, "places verified for this frame")
    geometry_ok: bool = _f(False, "geometric check passed (before the temporal check)")
    temporal_ok: bool | None = _f(None, "temporal check passed (null: the check is off)")
    nfa: float | None = _f(None, (
        "log10 number of false alarms of the geometry: how many times that much support is expected by chance "
        "among the pair's matches (a-contrario test); verified needs it below the configured bound (default -4); "
        "null: no geometry fitted"), since="1.3")
    geometry_reason: str | None = _f(None, (
        "why verification failed: '' when verified, else no_evidence (too few keypoints or matches to fit a "
        "model), chance, degenerate, collinear, clustered, cheirality, temporal, tie (another stored frame that "
        "is not a neighbour had like evidence), ...; null: nothing verified"),
        since="1.3")
    sequence_nfa: float | None = _f(None, (
        "verified by evidence over consecutive frames (DetectorConfig.sequence): the summed log10 NFA of the chain "
        "of frames ending here, whose last link is this frame's verified_place (nfa is that pair's own); null "
        "when one pair passed alone or nothing was verified"), since="1.5")
    verified_robot: str | None = _f(None, (
        "the fleet robot whose place was verified (run --fleet): verified_frame is then that robot's frame number "
        "and verified_place is null; null: a place of this node's own map (or nothing verified)"), since="1.6")
    candidates: list[Candidate] = field(default_factory=list, metadata=_meta(
        "the top places of the ranking (CandidateConfig.top_k) and every other place checked (track, "
        "island)", since="1.3"))
    score_kind: str | None = _f(None, "what score holds (null: not told, logs before format 1.1)",
                                enum=SCORE_KINDS, since="1.1")
    frame_seq: int | None = _f(None, "publisher sequence number of the frame (live runs only)")
    latency_ms: float | None = _f(None, "frame taken from the node's ring -> result, ms (live runs only)")
    age_ms: float | None = _f(None, "capture stamp -> result, ms; meaningful with synchronised clocks (live runs only)")

    def to_dict(self) -> dict:
        """The JSON object; transport fields appear only when set (live runs)."""
        d = dataclasses.asdict(self)
        for name in TRANSPORT_FIELDS:
            if d[name] is None:
                del d[name]
        return d


# ============================================================================ stats


@dataclass
class RemoteRobotStats:
    """One other robot of the fleet, as this node sees it (cumulative)."""

    places: int = _f(0, "its places this node holds now")
    summaries: int = _f(0, "place summaries received from it")
    refused: dict[str, int] = field(default_factory=dict, metadata=_meta("its messages refused, by reason"))
    fetches: int = _f(0, "keypoint fetches asked of it")
    fetch_failures: int = _f(0, "fetches that gave nothing usable (timeout, bad reply, robot gone)")
    bytes_in: int = _f(0, "bytes received from it: summaries and keypoint replies")
    fetch_ms_p50: float | None = _f(None, "median latency of its recent fetches, ms (null: none yet)")
    loops: int = _f(0, "loops verified to its places")
    alive: bool = _f(True, "its liveliness token is present")
    map_restarts: int = _f(0, "times it came back with a new map epoch (its places were forgotten)", since="1.7")
    keypoint_replies: int = _f(0, "its keypoint queries this node answered (as the query names the asker)", since="1.7")
    bytes_out: int = _f(0, "bytes of those replies (summaries go to every robot at once: FleetStats.bytes_out)",
                        since="1.7")


@dataclass
class FleetStats:
    """A node's part in a fleet (run --fleet), cumulative."""

    fleet: str = _f(description="fleet name")
    robot: str = _f(description="this node's robot id")
    places_served: int = _f(0, "own places offered to the fleet now")
    summaries_out: int = _f(0, "place summaries published")
    keypoint_replies: int = _f(0, "keypoint queries answered")
    bytes_out: int = _f(0, "bytes sent to the fleet: summaries and keypoint replies")
    remote_places: int = _f(0, "other robots' places held now")
    remote_evicted: int = _f(0, "other robots' places evicted to stay within the caps")
    refused_elsewhere: dict[str, int] = field(default_factory=dict, metadata=_meta(
        "messages refused from robots this node holds no places of (unreadable, other bundle, too many robots)"))
    robots: dict[str, RemoteRobotStats] = field(default_factory=dict, metadata=_meta("per other robot"))


@dataclass
class LatencySummary:
    """Percentiles of the node's latency (ring -> result), ms; null before the first frame."""

    p50: float | None = _f(None, "median, ms")
    p95: float | None = _f(None, "95th percentile, ms")


@dataclass(kw_only=True)
class StatsMessage(_Message):
    """Cumulative statistics of a run, sent every stats period and at the end."""

    TITLE = "aefabmap.LcdStats"
    DESCRIPTION = "periodic statistics of a streaming run (cumulative counters)"

    stamp_ns: int = _f(description="wall-clock time of the message, ns since the Unix epoch")
    uptime_s: float = _f(description="seconds since the run started")
    frames_received: int = _f(description="frames taken from the transport (or read from the log)")
    frames_processed: int = _f(description="frames that gave a result")
    dropped: int = _f(description="frames lost: sequence gaps (ring overflow or network)")
    publisher_restarts: int = _f(0, "times a publisher's sequence started again")
    bad: dict[str, int] = field(metadata=_meta("frames refused, by reason"))
    bad_total: int = _f(init=False, description="sum of bad")
    last_bad: str = _f("", "message of the last refused frame ('' when none)")
    loops: int = _f(description="loop closures so far")
    rss_mb: float | None = _f(None, "resident memory of the process, MB (null where unknown)")
    latency_ms: LatencySummary = field(default_factory=LatencySummary,
                                       metadata=_meta("latency percentiles over the last frames"))
    fps: float | None = _f(None, "processed frames per second since the previous stats message")
    log_errors: int = _f(0, "log write errors so far (disk full, I/O error, ...); never fatal", since="1.2")
    log_state: str | None = _f(None, (
        "the log now: 'ok', 'images_stopped' (low disk space: results only), 'stopped' (no space: nothing "
        "logged), 'failed' (no file open after an error; retried), 'closed'; null: not told"),
        enum=LOG_STATES, since="1.2")
    fleet: FleetStats | None = _f(None, "the node's part in a fleet (null: not in one)", since="1.6")

    def __post_init__(self) -> None:
        self.bad_total = sum(self.bad.values())


# ============================================================================ run summary


@dataclass
class LocateAnswer(_Message):
    """The answer of a node's "where am I?" queryable (``<results key>/locate``): one image
    located in the map, nothing stored (LoopClosureDetector.locate)."""

    TITLE = "aefabmap.LocateAnswer"
    DESCRIPTION = "Where one image is in a node's map (its locate queryable); nothing is inserted."

    verified: bool = _f(False, "a place of the map verified geometrically")
    place: int | None = _f(None, "the verified place's id (null: none verified)")
    frame: int | None = _f(None, "the frame that made the verified place (null: none verified)")
    inliers: int = _f(0, "inliers of the accepted geometry")
    nfa: float | None = _f(None, "log10 number of false alarms of the accepted geometry (null: none verified)")
    geometry_model: str | None = _f(None, "F, E (calibrated camera) or H", enum=("F", "E", "H"))
    relative_rotation: list[list[float]] | None = field(default=None, metadata=_meta(
        "with a calibrated camera (model E): 3x3 row-major rotation R_pq of the image's camera relative to the "
        "place's camera; null otherwise"))
    relative_translation: list[float] | None = _f(None, "with relative_rotation: direction of t_pq, unit length")
    checked: int = _f(0, "pair checks made")
    places: int = _f(0, "places in the map")
    latency_ms: float | None = _f(None, "from the query's arrival to the answer (ms)")


@dataclass(kw_only=True)
class RunSummary(_Message):
    """What a streaming run did (the last line `aefabmap run` prints). Latencies in ms
    (receive -> result), RSS in MB, duration in s."""

    TITLE = "aefabmap.RunSummary"
    DESCRIPTION = "summary of one `aefabmap run`"

    frames_received: int = _f(description="frames taken from the transport")
    frames_processed: int = _f(description="frames that gave a result")
    dropped: int = _f(description="frames lost (sequence gaps)")
    bad: dict[str, int] = field(metadata=_meta("frames refused, by reason"))
    loops: int = _f(description="loop closures")
    duration_s: float = _f(description="run time, s")
    latency_ms_p50: float | None = _f(description="median latency, ms (null: no frame)")
    latency_ms_p95: float | None = _f(description="95th percentile latency, ms (null: no frame)")
    peak_rss_mb: float = _f(description="highest resident memory seen, MB (0 where unknown)")
    mcap_path: str = _f(description="the MCAP log written")
    images_logged: int = _f(description="images written to the log")
    result_key: str = _f(description="Zenoh key of the results")
    stats_key: str = _f(description="Zenoh key of the stats")
    log_files: list[str] = field(default_factory=list, metadata=_meta(
        "MCAP files this run created, in order (the last 100; some may since have been deleted by the log budget)", since="1.2"))
    log_files_deleted: int = _f(0, "files of the log set deleted to keep within the log budget", since="1.2")
    log_errors: int = _f(0, "log write errors (not fatal)", since="1.2")
    bad_total: int = _f(init=False, description="sum of bad")

    def __post_init__(self) -> None:
        self.bad_total = sum(self.bad.values())


# ============================================================================ status


@dataclass(kw_only=True)
class StatusMessage(_Message):
    """A running node's health, the answer to a query on its status key
    (runtime/aefabmap_runtime/adapters/health.py). Counters are cumulative since the node started."""

    TITLE = "aefabmap.RuntimeStatus"
    DESCRIPTION = "health of one running aefabmap node, answered on demand (Zenoh queryable)"

    stamp_ns: int = _f(description="wall-clock time of the answer, ns since the Unix epoch")
    zid: str = _f(description="Zenoh id of the node's session (its liveliness token is aefabmap/runtime/<zid>)")
    aefabmap_version: str = _f(description="version of the aefabmap package running")
    message_format_version: str = _f(description="MESSAGE_FORMAT_VERSION of the node's messages")
    bundle_id: str | None = _f(None, "sha256 of the bundle manifest in canonical JSON (null: no manifest)")
    uptime_s: float = _f(description="seconds since the node started")
    image_key: str = _f(description="Zenoh key the node subscribes to for frames")
    results_key: str = _f(description="Zenoh key of its results (stats on <results_key>/stats)")
    frames_received: int = _f(description="frames taken from the transport")
    frames_processed: int = _f(description="frames that gave a result")
    dropped: int = _f(description="frames lost: sequence gaps (ring overflow or network)")
    bad: dict[str, int] = field(metadata=_meta("frames refused, by reason"))
    bad_total: int = _f(init=False, description="sum of bad")
    loops: int = _f(0, "loop closures so far")
    places: int | None = _f(None, "places in the map (null: before the first frame)")
    map_mb: float | None = _f(None, "memory of the map as the detector accounts it, MB (null: not told)")
    rss_mb: float | None = _f(None, "resident memory of the process, MB (null where unknown)")
    stage_ms: dict[str, float] = field(default_factory=dict, metadata=_meta(
        "median detector time per stage over the recent frames, ms (the results' timings_ms)"))
    recent_frames: int = _f(0, "frames behind stage_ms")
    log_files: int = _f(0, "MCAP files of this run still on disk")
    log_bytes: int = _f(0, "bytes of those files")
    log_errors: int = _f(0, "log write errors so far (never fatal)")
    log_state: str | None = _f(None, "the log now (see StatsMessage.log_state)", enum=LOG_STATES)
    warnings: list[str] = field(default_factory=list, metadata=_meta(
        "what the node warns about now, one line each, e.g. results that no ROS 2 subscriber can read "
        "(empty: nothing)", since="1.5"))
    fleet: FleetStats | None = _f(None, "the node's part in a fleet (null: not in one)", since="1.6")
    ros_topic_published: bool | None = _f(
        None, "ROS 2 runs: whether the image topic (--ros-topic) has a publisher in the graph or sent an image; "
        "false from 3 s after the start while it has neither (null: not a ROS 2 run, or before then)", since="1.8")
    ros_image_topics: list[str] = field(default_factory=list, metadata=_meta(
        "when ros_topic_published is false: the sensor_msgs Image and CompressedImage topics that are published, "
        "'<topic> (<type>)', those outside the run's domain or bridge namespace followed by ' in <where>'",
        since="1.8"))

    def __post_init__(self) -> None:
        self.bad_total = sum(self.bad.values())


__all__ = [
    "LOG_STATES",
    "MESSAGE_FORMAT_VERSION",
    "SCORE_KINDS",
    "TRANSPORT_FIELDS",
    "FleetStats",
    "FrameResult",
    "LatencySummary",
    "RemoteRobotStats",
    "RunSummary",
    "StatsMessage",
    "StatusMessage",
    "check_readable",
    "parse_version",
]
