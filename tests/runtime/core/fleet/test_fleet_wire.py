"""Fleet messages (runtime/aefabmap_runtime/core/fleet/fleet_wire.py): they round-trip, and whatever a hostile peer
sends is refused with a counted reason before anything is kept."""

from __future__ import annotations

import struct
from dataclasses import replace

import numpy as np
import pytest

from aefabmap_runtime.errors import ConfigError
from aefabmap_runtime.core.features.feature_kinds import get_kind
from aefabmap_runtime.core.fleet.fleet_wire import (
    MAX_REPLY_KEYPOINTS,
    FleetMessageError,
    PlaceSummary,
    check_token,
    decode_keypoints,
    encode_keypoints,
    fleet_key,
)
from aefabmap_runtime.core.map.keypoint_store import KeypointStore

ID = bytes(range(32))
OTHER = bytes(32)
V = 3000


def _summary(words=(3, 17, 2999), robot="a", frame=12) -> PlaceSummary:
    return PlaceSummary(robot, ID, frame, 1_700_000_000_000_000_000, np.array(words, np.int64))


def _store() -> KeypointStore:
    return KeypointStore(get_kind("orb"), V)


def _place(store: KeypointStore, n: int = 5):
    rng = np.random.default_rng(0)
    words = rng.integers(0, V, n)
    words[0] = -1  # a keypoint kept for geometry only
    xy = rng.uniform(0, 1, (n, 2)) * (319, 239)  # (x, y) inside the 240 x 320 image
    return store.pack(xy, words, rng.integers(0, 256, (n, 32), dtype=np.uint8), (240, 320))


def test_summary_round_trip_and_key():
    s = _summary()
    back = PlaceSummary.decode(s.encode(), ID, V)
    assert (back.robot, back.frame, back.stamp_ns, back.words.tolist()) == ("a", 12, s.stamp_ns, [3, 17, 2999])
    assert back.epoch == 0 and PlaceSummary.decode(replace(s, epoch=2**64 - 1).encode(), ID, V).epoch == 2**64 - 1
    wide = _summary(words=(1, 70_000))
    assert PlaceSummary.decode(wide.encode(), ID, 100_000).words.tolist() == [1, 70_000]
    assert fleet_key("f", "a", "place", "12") == "aefabmap/fleet/f/a/place/12"


@pytest.mark.parametrize("token", ["", "a/b", "*", "**", "a$b", "a?b", "a#b", "x" * 33, None, 5])
def test_robot_ids_and_fleet_names_are_plain_tokens(token):
    with pytest.raises(ConfigError):
        check_token(token, "robot id")


def _bad_summaries() -> dict[str, tuple[bytes, str]]:
    good = _summary().encode()
    head = 4 + 1 + 1 + 32 + 8 + 8 + 8 + 4 + 1
    out = {
        "empty": (b"", "malformed"),
        "truncated": (good[:-1], "malformed"),
        "trailing": (good + b"\0", "malformed"),
        "magic": (b"XXXX" + good[4:], "malformed"),
        "version": (good[:4] + b"\x09" + good[5:], "malformed"),
        "other bundle": (PlaceSummary("a", OTHER, 1, 0, np.array([1])).encode(), "other_bundle"),
        "word beyond the vocabulary": (_summary(words=(1, V)).encode(), "malformed"),
        "unsorted words": (_summary(words=(5, 4)).encode(), "malformed"),
        "repeated words": (_summary(words=(5, 5)).encode(), "malformed"),
        "negative frame": (_summary(frame=-1).encode(), "malformed"),
        "wildcard robot": (good[:head] + b"*" + good[head + 1:], "malformed"),
        "not utf-8 robot": (good[:head] + b"\xff" + good[head + 1:], "malformed"),
    }
    # a word count larger than the vocabulary (a peer asking us to read a huge array)
    fields = list(struct.unpack_from("<4sBB32sQqqIB", good))
    fields[7] = 2**32 - 1
    out["huge count"] = (struct.pack("<4sBB32sQqqIB", *fields) + good[head:], "malformed")
    fields[7], fields[8] = 3, 3
    out["odd width"] = (struct.pack("<4sBB32sQqqIB", *fields) + good[head:], "malformed")
    return out


@pytest.mark.parametrize("case", sorted(_bad_summaries()))
def test_hostile_summaries_are_refused_with_a_reason(case):
    data, reason = _bad_summaries()[case]
    with pytest.raises(FleetMessageError) as err:
        PlaceSummary.decode(data, ID, V)
    assert err.value.reason == reason


def test_keypoint_reply_round_trip():
    store = _store()
    place = _place(store)
    back = decode_keypoints(encode_keypoints(ID, 7, place, 5), ID, 7, store.dtype, V, store.no_word_code, 5)
    assert back.image_shape == (240, 320)
    assert np.array_equal(back.records, place.records)
    assert back.words[0] == -1 and np.array_equal(back.words[1:], place.words[1:])


def _bad_replies() -> dict[str, tuple[bytes, int, str]]:
    store = _store()
    good = encode_keypoints(ID, 7, _place(store))
    records = _place(store).records.copy()
    records["word"][2] = V + 5
    bad_word = encode_keypoints(ID, 7, type(_place(store))(records, (240, 320)))
    beyond = {}
    for name, shape, column in (("x at the long side's end", (192, 240), 0), ("y below the image", (240, 320), 1)):
        records = _place(store).records.copy()
        records["xy"][1, column] = 65535 if column == 0 else 65535 * 241 // 320  # x = 240 px of 240; y = 241 px of 240
        beyond[name] = (encode_keypoints(ID, 7, type(_place(store))(records, shape)), 7, "out_of_image")
    head = struct.Struct("<4sB32sQqHHIH")
    fields = list(head.unpack_from(good))

    def with_field(i, value):
        f = list(fields)
        f[i] = value
        return head.pack(*f) + good[head.size:]

    return {
        "empty": (b"", 7, "malformed"),
        "truncated": (good[:-3], 7, "malformed"),
        "magic": (b"AEFS" + good[4:], 7, "malformed"),
        "other bundle": (encode_keypoints(OTHER, 7, _place(store)), 7, "other_bundle"),
        "another frame": (good, 8, "malformed"),
        "word beyond the vocabulary": (bad_word, 7, "malformed"),
        "record size": (with_field(8, 40), 7, "malformed"),
        "too many keypoints": (with_field(7, MAX_REPLY_KEYPOINTS + 1), 7, "malformed"),
        "zero height": (with_field(5, 0), 7, "malformed"),
        "another map epoch": (with_field(3, 99), 7, "other_epoch"),
        **beyond,
    }


@pytest.mark.parametrize("case", sorted(_bad_replies()))
def test_hostile_keypoint_replies_are_refused_with_a_reason(case):
    store = _store()
    data, frame, reason = _bad_replies()[case]
    with pytest.raises(FleetMessageError) as err:
        decode_keypoints(data, ID, frame, store.dtype, V, store.no_word_code)
    assert err.value.reason == reason
