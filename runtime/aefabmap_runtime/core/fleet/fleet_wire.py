"""What robots of a fleet send each other (pure): place summaries and keypoint replies.

A **summary** announces one stored place: the robot, the bundle identity, the map epoch, the
frame number, the capture stamp and the place's sorted word ids. The **epoch** is a random number
a map draws when it starts empty and keeps in its state (LoopClosureDetector.map_epoch): frame
numbers count within one epoch (a robot restarted without its map numbers its frames from 0
again), so a new epoch tells the others to forget the old places. A **keypoint reply** carries a
place's verification keypoints in the keypoint store's record form
(runtime/aefabmap_runtime/core/map/keypoint_store.py), with the epoch, sent only when another
robot asks for them. An **epoch reply** tells the robot's current map epoch. All are
little-endian binary with a magic, a version and the bundle identity, and all are read as
hostile input: every size, count, id and position is checked before anything is kept; a bad
message raises FleetMessageError with a short reason that the node counts.

Key expressions (`fleet_key`): ``aefabmap/fleet/<fleet>/<robot>/place/<frame>`` (summaries),
``.../keypoints/<frame>[?robot=ID]`` (the keypoint queryable; the asker names itself),
``.../summaries[?after=N]`` (a robot's summaries, of frames after N: for a robot that joins late,
or comes back), ``.../epoch`` (its map epoch) and ``.../alive/<session id>`` (its liveliness
token, naming the Zenoh session that speaks for the robot: replies from any other session are
not believed).
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass

import numpy as np

from aefabmap_runtime.errors import ConfigError, InputError
from aefabmap_runtime.core.map.keypoint_store import PlaceKeypoints

WIRE_VERSION = 3
SUMMARY_MAGIC = b"AEFS"
KEYPOINTS_MAGIC = b"AEFK"
EPOCH_MAGIC = b"AEFE"
#: Fleet names and robot ids: a short token that cannot be a key-expression wildcard or separator.
TOKEN_PATTERN = re.compile(r"[A-Za-z0-9_-]{1,32}")
#: Most keypoints a reply may carry (the store keeps at most VerificationConfig.keypoints).
MAX_REPLY_KEYPOINTS = 8192
#: Largest image side a reply may state (pixels).
MAX_IMAGE_SIDE = 16384

# magic, version, robot length, identity, epoch, frame, stamp_ns, word count, word width (2 or 4 bytes)
_SUMMARY_HEAD = struct.Struct("<4sBB32sQqqIB")
# magic, version, identity, epoch, frame, height, width, keypoint count, record size
_KEYPOINTS_HEAD = struct.Struct("<4sB32sQqHHIH")
# magic, version, identity, epoch
_EPOCH = struct.Struct("<4sB32sQ")
#: Positions are stored in 1/65535 of the image's longer side (keypoint_store.py).
_XY_SCALE = 65535


class FleetMessageError(InputError):
    """A fleet message that cannot be used; `reason` is the counter it goes under."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


def _unpack_head(data: bytes, head: struct.Struct, what: str) -> tuple:
    if len(data) < head.size:
        raise FleetMessageError("malformed", f"{what} of {len(data)} bytes is shorter than its header")
    return head.unpack_from(data)


def _check_head(magic: bytes, version: int, ident: bytes, want_magic: bytes, identity: bytes, what: str) -> None:
    """This message kind and wire version, from a robot with this node's bundle."""
    if magic != want_magic or version != WIRE_VERSION:
        raise FleetMessageError("malformed", f"not a version-{WIRE_VERSION} {what}")
    if ident != identity:
        raise FleetMessageError("other_bundle", f"{what} from a robot with another bundle")


def check_token(text: object, what: str) -> str:
    """`text` as a fleet name or robot id (TOKEN_PATTERN), else ConfigError."""
    if not isinstance(text, str) or not TOKEN_PATTERN.fullmatch(text):
        raise ConfigError(f"{what} must be 1-32 letters, digits, '_' or '-' (no '/', '*', '$', '?', '#'), "
                          f"got {str(text)[:40]!r}")
    return text


def max_summary_bytes(vocabulary_size: int) -> int:
    """The largest summary a robot with a bundle of this vocabulary can send (every word, 4 bytes each)."""
    return _SUMMARY_HEAD.size + 32 + 4 * int(vocabulary_size)


def fleet_key(fleet: str, robot: str, *rest: str) -> str:
    """``aefabmap/fleet/<fleet>/<robot>/<rest...>`` (fleet and robot may be "*" to match all)."""
    return "/".join(("aefabmap", "fleet", fleet, robot, *rest))


@dataclass(frozen=True)
class PlaceSummary:
    """One stored place of a robot: its sorted unique word ids (int64) and where it came from;
    identity: the 32 bytes of its bundle's id (runtime/aefabmap_runtime/adapters/state_dir.py bundle_id); epoch:
    the robot's map epoch (see the module doc)."""

    robot: str
    identity: bytes
    frame: int
    stamp_ns: int
    words: np.ndarray
    epoch: int = 0

    def encode(self) -> bytes:
        wide = self.words.size and int(self.words.max()) > 0xFFFF
        words = np.ascontiguousarray(self.words, "<u4" if wide else "<u2")
        robot = self.robot.encode()
        head = _SUMMARY_HEAD.pack(SUMMARY_MAGIC, WIRE_VERSION, len(robot), self.identity, self.epoch, self.frame,
                                  self.stamp_ns, words.size, words.itemsize)
        return head + robot + words.tobytes()

    @classmethod
    def decode(cls, data: bytes, identity: bytes, vocabulary_size: int) -> PlaceSummary:
        """A summary from bytes, checked against this node's bundle identity and vocabulary size."""
        magic, version, robot_len, ident, epoch, frame, stamp_ns, n, width = _unpack_head(data, _SUMMARY_HEAD,
                                                                                           "summary")
        _check_head(magic, version, ident, SUMMARY_MAGIC, identity, "summary")
        if width not in (2, 4) or n > vocabulary_size or frame < 0:
            raise FleetMessageError("malformed", f"summary with {n} words of {width} bytes, frame {frame}")
        if len(data) != _SUMMARY_HEAD.size + robot_len + n * width:
            raise FleetMessageError("malformed", f"summary of {len(data)} bytes does not match its header")
        try:
            robot = check_token(data[_SUMMARY_HEAD.size:_SUMMARY_HEAD.size + robot_len].decode(), "robot id")
        except (UnicodeDecodeError, ConfigError) as exc:
            raise FleetMessageError("malformed", f"summary robot id: {exc}") from exc
        words = np.frombuffer(data, "<u2" if width == 2 else "<u4", n, _SUMMARY_HEAD.size + robot_len).astype(np.int64)
        if n and (int(words[-1]) >= vocabulary_size or np.any(np.diff(words) <= 0)):
            raise FleetMessageError("malformed", "summary words are not sorted unique ids of this vocabulary")
        return cls(robot, ident, int(frame), int(stamp_ns), words, int(epoch))


def encode_keypoints(identity: bytes, frame: int, place: PlaceKeypoints, epoch: int = 0) -> bytes:
    """A keypoint reply: the place's records as the store holds them."""
    records = np.ascontiguousarray(place.records)
    head = _KEYPOINTS_HEAD.pack(KEYPOINTS_MAGIC, WIRE_VERSION, identity, epoch, frame, place.image_shape[0],
                                place.image_shape[1], records.shape[0], records.dtype.itemsize)
    return head + records.tobytes()


def decode_keypoints(data: bytes, identity: bytes, frame: int, dtype: np.dtype, vocabulary_size: int,
                     no_word: int, epoch: int = 0) -> PlaceKeypoints:
    """A keypoint reply for `frame` of map `epoch`, checked: this bundle, this store's record form
    `dtype`, word ids below vocabulary_size or the store's no-word code, a plausible image size."""
    magic, version, ident, got_epoch, got_frame, height, width, n, size = _unpack_head(data, _KEYPOINTS_HEAD,
                                                                                      "keypoint reply")
    _check_head(magic, version, ident, KEYPOINTS_MAGIC, identity, "keypoint reply")
    if got_frame != frame:
        raise FleetMessageError("malformed", f"keypoint reply for frame {got_frame}, asked for {frame}")
    if got_epoch != epoch:  # the robot restarted: its frame numbers mean other places now
        raise FleetMessageError("other_epoch", f"keypoint reply of map epoch {got_epoch}, held {epoch}")
    if size != dtype.itemsize or n > MAX_REPLY_KEYPOINTS or not (0 < height <= MAX_IMAGE_SIDE and 0 < width <= MAX_IMAGE_SIDE):
        raise FleetMessageError("malformed", f"keypoint reply of {n} records of {size} bytes, image {height}x{width}")
    if len(data) != _KEYPOINTS_HEAD.size + n * size:
        raise FleetMessageError("malformed", f"keypoint reply of {len(data)} bytes does not match its header")
    records = np.frombuffer(data, dtype, n, _KEYPOINTS_HEAD.size).copy()
    words = records["word"].astype(np.int64)
    if np.any((words != no_word) & ((words < 0) | (words >= vocabulary_size))):
        raise FleetMessageError("malformed", "keypoint reply holds word ids outside the vocabulary")
    # Positions are fractions of the longer side: each must fall inside its own side of the image.
    units = records["xy"].astype(np.int64) * max(height, width)
    if n and (np.any(units[:, 0] >= width * _XY_SCALE) or np.any(units[:, 1] >= height * _XY_SCALE)):
        raise FleetMessageError("out_of_image", f"keypoint reply with positions outside its {height}x{width} image")
    return PlaceKeypoints(records, (int(height), int(width)))


def encode_epoch(identity: bytes, epoch: int) -> bytes:
    """An epoch reply: the robot's current map epoch."""
    return _EPOCH.pack(EPOCH_MAGIC, WIRE_VERSION, identity, epoch)


def decode_epoch(data: bytes, identity: bytes) -> int:
    """The map epoch of an epoch reply, checked against this node's bundle identity."""
    if len(data) != _EPOCH.size:
        raise FleetMessageError("malformed", f"epoch reply of {len(data)} bytes, not {_EPOCH.size}")
    magic, version, ident, epoch = _EPOCH.unpack(data)
    _check_head(magic, version, ident, EPOCH_MAGIC, identity, "epoch reply")
    return int(epoch)
