"""The run configuration: everything that decides a run's results, as one typed, frozen record.

`RunConfig` is what `run`, `eval`, `replay` and `slam` build (aefabmap/cli/options.py builds
it from options or a profile), what `run` writes whole into its log's metadata and its state
directory, and what `replay` reads back whole (`logged_run_config`, older logs included), so a
replay decides every frame as the run did. The dict form is plain JSON; reading it back checks
every key and type (logs and state files are input like any other).
"""

from __future__ import annotations

import dataclasses
import json
import types
import typing
from dataclasses import dataclass, field

from aefabmap_runtime.errors import ConfigError
from aefabmap_runtime.core.detector import DetectorConfig
from aefabmap_runtime.core.fleet.fleet_map import FleetConfig

#: Version of RunConfig's dict form.
RUN_CONFIG_FORMAT = 1
#: Most frames a node may buffer: a queue is for bursts, not for hours of backlog.
MAX_QUEUE = 10_000
#: Most threads a run may work on frames with (a board has 4 cores; more gains nothing and costs memory).
MAX_WORKERS = 16
#: Key of the RunConfig inside a log's run metadata (aefabmap.run_config), beside the transport's settings.
RUN_CONFIG_KEY = "run"


@dataclass(frozen=True)
class RunConfig:
    """One run's settings.

    model: the bundle path as given (a replay may load the same bundle from elsewhere).
    detector: every detector setting (features budget, scorer, candidate policy, verification,
        camera, map caps, temporal check).
    profile: the preset the settings came from (runtime/aefabmap_runtime/core/profiles.py), or None.
    queue: frames the live node buffers between the transport and the detector.
    fleet: the fleet the live node joins (run --fleet; None: none); its remote loops depend on
        what other robots offered, so a replay cannot decide them again.
    workers: threads that work on frames, the next frames prepared while one is decided
        (runtime/aefabmap_runtime/adapters/frame_pipeline.py); the results do not depend on it.
    localize: the map of the run's state directory is only read (core/map/place_map.py read_only):
        frames are ranked and verified against it, none is inserted, nothing is evicted or written.
    """

    model: str = ""
    detector: DetectorConfig = field(default_factory=DetectorConfig)
    profile: str | None = None
    queue: int = 2
    fleet: FleetConfig | None = None
    workers: int = 1
    localize: bool = False

    def __post_init__(self) -> None:
        check_workers(self.workers)
        if not isinstance(self.localize, bool):
            raise ConfigError(f"localize must be true or false, got {str(self.localize)[:40]}")
        if self.fleet is not None and not isinstance(self.fleet, FleetConfig):
            raise ConfigError(f"fleet must be a FleetConfig, got {type(self.fleet).__name__}")
        if not isinstance(self.detector, DetectorConfig):
            raise ConfigError(f"detector must be a DetectorConfig, got {type(self.detector).__name__}")
        if not isinstance(self.queue, int) or isinstance(self.queue, bool) or not 1 <= self.queue <= MAX_QUEUE:
            raise ConfigError(f"queue must be an integer in [1, {MAX_QUEUE}], got {str(self.queue)[:40]}")

    def to_dict(self) -> dict:
        """Plain JSON-able dict (tuples become lists), with the format version."""
        return {"format": RUN_CONFIG_FORMAT, **json.loads(json.dumps(dataclasses.asdict(self)))}

    @classmethod
    def from_dict(cls, doc: object) -> RunConfig:
        """Read `to_dict()`'s output back; ConfigError on an unknown key, a wrong type or a bad value."""
        if not isinstance(doc, dict):
            raise ConfigError(f"run configuration must be an object, got {type(doc).__name__}")
        doc = dict(doc)
        version = doc.pop("format", None)
        if version != RUN_CONFIG_FORMAT:
            raise ConfigError(f"run configuration format {str(version)[:20]!r} is not {RUN_CONFIG_FORMAT}")
        return _from_plain(cls, doc, "run")

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> RunConfig:
        try:
            doc = json.loads(text)
        except (ValueError, RecursionError) as exc:
            raise ConfigError(f"run configuration is not JSON: {exc}") from exc
        return cls.from_dict(doc)


def check_workers(workers) -> int:
    """`workers` as an int in [1, MAX_WORKERS] (ConfigError otherwise)."""
    if not isinstance(workers, int) or isinstance(workers, bool) or not 1 <= workers <= MAX_WORKERS:
        raise ConfigError(f"workers must be an integer in [1, {MAX_WORKERS}], got {str(workers)[:40]}")
    return workers


def _from_plain(cls, doc: object, where: str):
    """An instance of dataclass `cls` from its plain dict, every field's type checked."""
    if not isinstance(doc, dict):
        raise ConfigError(f"{where} must be an object, got {type(doc).__name__}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(str(k)[:40] for k in doc if k not in names)
    if unknown:
        raise ConfigError(f"{where}: unknown setting(s) {', '.join(unknown)}")
    values = {k: _value(hints[k], v, f"{where}.{k}") for k, v in doc.items()}
    try:
        return cls(**values)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{where}: {exc}") from exc


def _value(tp, v, where: str):
    """`v` checked against annotation `tp` (dataclass, int, float, bool, str, None, unions of these,
    tuple[float, ...] / fixed tuples, dict of str to numbers)."""
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        errors = []
        for arm in typing.get_args(tp):
            try:
                return _value(arm, v, where)
            except ConfigError as exc:
                if arm is not type(None):  # "must be null" explains nothing when a value was meant
                    errors.append(str(exc))
        raise ConfigError(errors[0] if errors else f"{where}: bad value")
    if tp is type(None):
        if v is None:
            return None
        raise ConfigError(f"{where} must be null, got {str(v)[:40]}")
    if dataclasses.is_dataclass(tp):
        return _from_plain(tp, v, where)
    if origin is tuple:
        args = typing.get_args(tp)
        if not isinstance(v, list):
            raise ConfigError(f"{where} must be a list, got {type(v).__name__}")
        arms = [args[0]] * len(v) if len(args) == 2 and args[1] is Ellipsis else list(args)
        if len(arms) != len(v):
            raise ConfigError(f"{where} must have {len(arms)} entries, got {len(v)}")
        return tuple(_value(a, x, where) for a, x in zip(arms, v))
    if tp is bool:
        if isinstance(v, bool):
            return v
    elif tp is int:
        if isinstance(v, int) and not isinstance(v, bool):
            return v
    elif tp is float:
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            return float(v)
    elif tp is str:
        if isinstance(v, str):
            return v
    else:
        raise ConfigError(f"{where}: settings of type {tp} cannot be read back")
    raise ConfigError(f"{where} must be {getattr(tp, '__name__', tp)}, got {str(v)[:40]!r}")


def settings_differences(stored: object, current: object, prefix: str = "") -> list[str]:
    """Dotted names of the settings that differ between two plain dicts (e.g. a map state's
    recorded detector settings and this run's), at most the first 20."""
    if isinstance(stored, dict) and isinstance(current, dict):
        out: list[str] = []
        for key in sorted(set(stored) | set(current), key=str):
            out += settings_differences(stored.get(key), current.get(key), f"{prefix}{key}.")
        return out[:20]
    return [] if stored == current else [prefix.rstrip(".")]


#: Settings added after logs and maps were first recorded: (section, key, the value a record
#: without the key ran with). Verification without `upright`: before upright descriptors; candidates
#: without `retry_alone`: FAB-MAP's retried candidates were checked by same-word matching first;
#: chains or candidates without `margin_log10_nfa`: a chain or a passing pair was taken without a
#: margin over rival stored frames; candidates without `track_direction`: the track ran forwards only.
_ADDED_LATER = (("verification", "upright", False), ("candidates", "retry_alone", False),
                ("candidates", "margin_log10_nfa", 0.0), ("sequence", "margin_log10_nfa", 0.0),
                ("candidates", "track_direction", False))


def settings_as_they_ran(detector: object) -> object:
    """Recorded detector settings (DetectorConfig.to_dict, or part of it) as they ran: a section
    recorded without a setting added later gets the value it ran with (`_ADDED_LATER`).
    Anything else comes back as it is."""
    if not isinstance(detector, dict):
        return detector
    for section, key, ran_with in _ADDED_LATER:
        settings = detector.get(section)
        if isinstance(settings, dict) and key not in settings:
            detector = {**detector, section: {**settings, key: ran_with}}
    return detector


def recorded_settings_differences(recorded: object, config: DetectorConfig) -> list[str]:
    """Dotted names of the detector settings in which ``recorded`` (the JSON text a map state or
    journal stored, DetectorConfig.to_dict) differs from ``config``, ignoring the kept inlier
    points (they change what is drawn, never a decision); ["(unreadable record)"] when the
    text cannot be read."""
    try:
        differ = settings_differences(settings_as_they_ran(json.loads(recorded)), config.to_dict())
    except (TypeError, ValueError, RecursionError):
        return ["(unreadable record)"]
    return [d for d in differ if not d.endswith("keep_inlier_points")]


def logged_run_config(logged: object) -> RunConfig:
    """The RunConfig a run wrote into its log's run metadata (`logged`: that record). Logs written
    before the whole configuration was kept carry only the map caps and the camera (they ran as
    _BEFORE_WHOLE_CONFIG says); ConfigError when the record is malformed."""
    if not isinstance(logged, dict):
        raise ConfigError("the log's run configuration is not an object")
    if RUN_CONFIG_KEY in logged:
        doc = logged[RUN_CONFIG_KEY]
        detector = doc.get("detector") if isinstance(doc, dict) else None
        if isinstance(detector, dict) and "sequence" not in detector:
            detector = {**detector, **_BEFORE_CHAINS}
        if isinstance(detector, dict):
            doc = {**doc, "detector": settings_as_they_ran(detector)}
        return RunConfig.from_dict(doc)
    legacy = {k: logged.get(k) for k in ("max_places", "memory_mb")}
    camera = logged.get("camera")
    detector = {**legacy, "verification": {"camera": camera}, **_BEFORE_WHOLE_CONFIG}
    doc = {"format": RUN_CONFIG_FORMAT, "model": str(logged.get("model", ""))[:4096],
           "detector": settings_as_they_ran(detector)}
    return RunConfig.from_dict(doc)


#: Logs written before evidence over consecutive frames existed ran without it.
_BEFORE_CHAINS = {"sequence": {"frames": 0}}
#: Logs written before the whole configuration was kept also retried only FAB-MAP's best candidate
#: and kept the track for 3 frames.
_BEFORE_WHOLE_CONFIG = {**_BEFORE_CHAINS, "candidates": {"bruteforce_fallback": 1, "track_memory": 3}}
