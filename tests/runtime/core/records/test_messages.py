"""Wire messages (runtime/aefabmap_runtime/core/records/messages.py) and the schema generator/validator (json_schema.py)."""

from __future__ import annotations

import dataclasses
import json
import math

import pytest

from aefabmap_runtime.errors import InputError
from aefabmap_runtime.core.records.json_schema import schema_for_dataclass, validate
from aefabmap_runtime.core.records.messages import (
    MESSAGE_FORMAT_VERSION,
    TRANSPORT_FIELDS,
    FrameResult,
    LatencySummary,
    RunSummary,
    StatsMessage,
    check_readable,
    parse_version,
)


def _result(**fields) -> FrameResult:
    base = dict(sequence=3, stamp_ns=10**18, n_keypoints=400, n_words=200, best_place=1, best_frame=0,
                score=0.97, p_new=0.01, loop=True)
    return FrameResult(**{**base, **fields})


def _stats(**fields) -> StatsMessage:
    base = dict(stamp_ns=1, uptime_s=0.5, frames_received=0, frames_processed=0, dropped=0,
                bad={"corrupt": 0, "rejected": 0}, loops=0)
    return StatsMessage(**{**base, **fields})


@pytest.mark.parametrize("cls", [FrameResult, StatsMessage, RunSummary])
def test_schema_has_every_field_and_requires_those_without_default(cls):
    schema = cls.json_schema()
    names = [f.name for f in dataclasses.fields(cls)]
    assert list(schema["properties"]) == names
    assert schema["title"] == cls.TITLE and schema["type"] == "object"
    for f in dataclasses.fields(cls):
        required = f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING
        assert (f.name in schema["required"]) == required, f.name


def test_result_schema_nullability_enums_and_score_description():
    props = FrameResult.json_schema()["properties"]
    assert props["best_place"]["type"] == ["integer", "null"]
    assert props["score"]["type"] == "number"
    assert "llr" in props["score"]["description"] and "score_kind" in props["score"]["description"]
    assert props["score_kind"]["enum"] == ["probability", "llr", "similarity", None]
    assert props["geometry_model"]["enum"] == ["F", "E", "H", None]
    assert props["geometry"]["items"] == {"type": "array", "items": {"type": "number"}}
    assert props["timings_ms"]["additionalProperties"] == {"type": "number"}
    assert props["relative_rotation"]["type"] == ["array", "null"]
    assert props["relative_translation"]["items"] == {"type": "number"}
    assert "QUERY camera relative to the matched PLACE camera" in props["relative_rotation"]["description"]


def test_stats_schema_covers_what_the_node_sends_including_the_first_message_nulls():
    schema = StatsMessage.json_schema()
    assert {"publisher_restarts", "last_bad", "bad_total", "fps"} <= set(schema["properties"])
    first = _stats(rss_mb=None, latency_ms=LatencySummary(None, None), fps=0.0)
    doc = json.loads(first.to_json_bytes())
    assert doc["latency_ms"] == {"p50": None, "p95": None} and doc["rss_mb"] is None
    assert validate(doc, schema) is None
    assert doc["bad_total"] == 0 and _stats(bad={"corrupt": 2, "empty": 1}).bad_total == 3


def test_round_trips_and_transport_fields_only_when_set():
    replayed = _result(timings_ms={"features": 1.5}, geometry=[[1.0, 0, 0], [0, 1, 0], [0, 0, 1]], score_kind="llr",
                       geometry_model="E", relative_rotation=[[1.0, 0, 0], [0, 1, 0], [0, 0, 1]],
                       relative_translation=[0.6, 0.0, 0.8])
    doc = json.loads(replayed.to_json_bytes())
    assert not set(TRANSPORT_FIELDS) & set(doc)
    assert FrameResult.from_json(replayed.to_json_bytes()) == replayed
    live = dataclasses.replace(replayed, frame_seq=7, latency_ms=3.25, age_ms=4.0)
    assert json.loads(live.to_json_bytes())["frame_seq"] == 7
    assert FrameResult.from_json(live.to_json_bytes()) == live
    stats = _stats(rss_mb=120.5, latency_ms=LatencySummary(2.0, 3.0), fps=8.0, last_bad="corrupt frame")
    assert StatsMessage.from_json(stats.to_json_bytes()) == stats
    summary = RunSummary(frames_received=3, frames_processed=2, dropped=0, bad={"corrupt": 1}, loops=0,
                         duration_s=1.0, latency_ms_p50=None, latency_ms_p95=None, peak_rss_mb=0.0,
                         mcap_path="x.mcap", images_logged=2, result_key="a/lcd", stats_key="a/lcd/stats")
    assert json.loads(summary.to_json_bytes())["bad_total"] == 1
    assert RunSummary.from_json(summary.to_json_bytes()) == summary


def test_from_json_coerces_numbers_ignores_unknown_keys_and_keeps_nan():
    doc = json.loads(_result().to_json_bytes())
    doc.update(score=1, from_a_newer_minor_version=True, llr=float("nan"))
    res = FrameResult.from_json(json.dumps(doc).encode())
    assert isinstance(res.score, float) and res.score == 1.0 and math.isnan(res.llr)
    old = {k: v for k, v in doc.items() if k not in ("score_kind", "verified", "inliers")}
    parsed = FrameResult.from_json(old)  # an older log: optional fields take their defaults
    assert parsed.score_kind is None and parsed.verified is False and parsed.inliers == 0


@pytest.mark.parametrize(
    "change, words",
    [
        ({"score": "high"}, "'score': expected number, got string"),
        ({"sequence": True}, "'sequence': expected integer, got boolean"),
        ({"loop": None}, "'loop': expected boolean, got null"),
        ({"geometry_model": "X"}, "'geometry_model': 'X' is not one of"),
        ({"timings_ms": {"features": "slow"}}, "'timings_ms.features': expected number"),
        ({"geometry": [[1.0, "a"]]}, "'geometry[0][1]': expected number"),
    ],
)
def test_from_json_refuses_malformed_results_in_one_line(change, words):
    doc = {**json.loads(_result().to_json_bytes()), **change}
    with pytest.raises(InputError, match="aefabmap.LcdResult") as err:
        FrameResult.from_json(json.dumps(doc))
    assert words in str(err.value) and "\n" not in str(err.value)


def test_from_json_refuses_missing_fields_non_json_and_non_objects():
    doc = json.loads(_result().to_json_bytes())
    del doc["stamp_ns"]
    with pytest.raises(InputError, match="missing required field 'stamp_ns'"):
        FrameResult.from_json(doc)
    with pytest.raises(InputError, match="not JSON"):
        FrameResult.from_json(b"\xff{not json")
    with pytest.raises(InputError, match="expected object, got array"):
        StatsMessage.from_json(b"[1, 2]")
    with pytest.raises(InputError, match="'latency_ms.p50': expected number or null"):
        StatsMessage.from_json({**json.loads(_stats().to_json_bytes()), "latency_ms": {"p50": "x"}})


def test_generator_refuses_types_it_cannot_express():
    @dataclasses.dataclass
    class Bad:
        x: int | str

    with pytest.raises(TypeError):
        schema_for_dataclass(Bad)


def test_versions():
    assert parse_version("1") == (1, 0) and parse_version("1.1") == (1, 1)
    assert check_readable("1") == (1, 0)
    assert check_readable(MESSAGE_FORMAT_VERSION) == parse_version(MESSAGE_FORMAT_VERSION)
    assert check_readable("1.99") == (1, 99)  # a newer minor only adds optional fields
    with pytest.raises(InputError, match="newer than this aefabmap reads"):
        check_readable("2.0")
    for bad in ("", "one", "1.2.3", "-1"):
        with pytest.raises(InputError, match="malformed"):
            parse_version(bad)
    pose = {"relative_rotation", "relative_translation"}
    chain = {"sequence_nfa"} | {"verified_robot"}
    assert set(FrameResult.fields_since((1, 0))) == {"score_kind", "nfa", "geometry_reason", "candidates"} | pose | chain
    assert set(FrameResult.fields_since((1, 2))) == {"nfa", "geometry_reason", "candidates"} | pose | chain
    assert set(FrameResult.fields_since((1, 3))) == pose | chain
    assert set(FrameResult.fields_since((1, 4))) == chain
    assert set(FrameResult.fields_since((1, 5))) == {"verified_robot"}
    assert FrameResult.fields_since(parse_version(MESSAGE_FORMAT_VERSION)) == ()
