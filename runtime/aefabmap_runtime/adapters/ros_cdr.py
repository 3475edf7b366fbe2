"""ROS 2 CDR for exactly the messages the runtime exchanges: sensor_msgs Image and
CompressedImage in, std_msgs/String and diagnostic_msgs/DiagnosticArray out.

A small, strict reader rather than a generic one: every length is checked against the
buffer before anything is sliced, and a malformed message raises :class:`FrameError` with
one reason of ``frames.BAD_FRAME_REASONS`` (``corrupt`` for broken CDR; the image's own
problems keep their usual reasons), never another exception. Used by the live rmw_zenoh
subscriber (runtime/aefabmap_runtime/adapters/rmw_zenoh.py) and by bag replay (runtime/aefabmap_runtime/adapters/ros_bag.py),
so both turn a message into a frame the same way.

Layout (OMG CDR / XCDR1, as rmw_zenoh and rosbag2 write it): a 4-byte encapsulation header
(``00 01`` little-endian, ``00 00`` big-endian; ``00 07``/``00 06``, plain XCDR2, has the same
layout for these types), then the fields, each aligned to its size counted from the end of
the header. A string is a uint32 length including the terminating NUL, then the bytes.

    Image: header (stamp int32 sec, uint32 nanosec; frame_id string), uint32 height,
           uint32 width, string encoding, uint8 is_bigendian, uint32 step, uint8[] data
    CompressedImage: header, string format, uint8[] data
    DiagnosticArray: header, uint32 count, then per status: uint8 level, string name,
           string message, string hardware_id, uint32 count, then per value: string key,
           string value

The message definitions at the end (MSGDEFS) are the schemas of the MCAP log's ros2 profile,
whose messages mcap-ros2-support serialises (runtime/aefabmap_runtime/adapters/rosbag2_mcap.py).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from aefabmap_runtime.adapters.frames import (
    FrameError,
    compressed_format_to_encoding,
    pack_raw_rows,
)

IMAGE_TYPE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE_TYPE = "sensor_msgs/msg/CompressedImage"
STRING_TYPE = "std_msgs/msg/String"
DIAGNOSTIC_ARRAY_TYPE = "diagnostic_msgs/msg/DiagnosticArray"
#: RIHS01 hash of std_msgs/msg/String (Iron and later; checked against rosbags in the tests).
STRING_RIHS01 = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
#: RIHS01 hash of sensor_msgs/msg/Image (for this node's subscription token on Iron and later).
IMAGE_RIHS01 = "RIHS01_d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47"
#: RIHS01 hash of sensor_msgs/msg/CompressedImage (checked against rosbags in the tests).
COMPRESSED_IMAGE_RIHS01 = "RIHS01_15640771531571185e2efc8a100baf923961a4d15d5569652e6cb6691e8e371a"
#: RIHS01 hash of diagnostic_msgs/msg/DiagnosticArray (checked against rosbags in the tests).
DIAGNOSTIC_ARRAY_RIHS01 = "RIHS01_5a8a36efb05fb25070fa0fb3810290c0e6cd4862b54a8fb975a1ee8dc55a333e"
RIHS01_OF = {IMAGE_TYPE: IMAGE_RIHS01, COMPRESSED_IMAGE_TYPE: COMPRESSED_IMAGE_RIHS01, STRING_TYPE: STRING_RIHS01,
             DIAGNOSTIC_ARRAY_TYPE: DIAGNOSTIC_ARRAY_RIHS01}


_LITTLE = {b"\x00\x01": True, b"\x00\x00": False, b"\x00\x07": True, b"\x00\x06": False}
#: Longest text field accepted (frame_id, encoding, format), bytes: real ones are tens of bytes.
MAX_TEXT_BYTES = 4096


class _Reader:
    """Cursor over one CDR message; every read is bounds-checked (FrameError ``corrupt``)."""

    def __init__(self, data: bytes | memoryview, what: str) -> None:
        self.buf = memoryview(data).cast("B") if not isinstance(data, (bytes, bytearray)) else memoryview(data)
        self.what = what
        if len(self.buf) < 4:
            self._fail(f"{len(self.buf)} bytes, shorter than the 4-byte CDR header")
        little = _LITTLE.get(bytes(self.buf[:2]))
        if little is None:
            self._fail(f"unknown CDR encapsulation {bytes(self.buf[:2]).hex()}")
        self.order = "<" if little else ">"
        self.pos = 4

    def _fail(self, why: str):
        raise FrameError("corrupt", f"{self.what}: {why}")

    def _align(self, n: int) -> None:
        self.pos += (-(self.pos - 4)) % n

    def _take(self, n: int, field: str) -> memoryview:
        if n < 0 or self.pos + n > len(self.buf):
            self._fail(f"{field} needs {n} bytes at offset {self.pos}, message has {len(self.buf)}")
        out = self.buf[self.pos : self.pos + n]
        self.pos += n
        return out

    def u8(self, field: str) -> int:
        return self._take(1, field)[0]

    def u32(self, field: str) -> int:
        self._align(4)
        return struct.unpack(self.order + "I", self._take(4, field))[0]

    def i32(self, field: str) -> int:
        self._align(4)
        return struct.unpack(self.order + "i", self._take(4, field))[0]

    def string(self, field: str) -> str:
        n = self.u32(field + " length")
        if n > MAX_TEXT_BYTES:
            self._fail(f"{field} of {n} bytes exceeds {MAX_TEXT_BYTES}")
        raw = bytes(self._take(n, field))
        if n and raw[-1] != 0:
            self._fail(f"{field} is not NUL-terminated")
        try:
            return raw[:-1].decode("utf-8") if n else ""
        except UnicodeDecodeError:
            self._fail(f"{field} is not UTF-8")

    def octets(self, field: str) -> memoryview:
        n = self.u32(field + " length")
        return self._take(n, field)

    def stamp_ns(self) -> int:
        sec = self.i32("header.stamp.sec")
        nanosec = self.u32("header.stamp.nanosec")
        if sec < 0 or nanosec >= 1_000_000_000:
            self._fail(f"header stamp {sec} s {nanosec} ns is out of range")
        return sec * 1_000_000_000 + nanosec


@dataclass(frozen=True)
class RosImage:
    """A decoded sensor_msgs Image or CompressedImage, as the frames contract needs it.

    payload/encoding: the frame for ``frames.decode_frame`` (raw rows repacked tightly);
    stamp_ns: the header stamp (ns; 0 when the publisher left it unset); frame_id: the
    header's frame id.
    """

    payload: bytes
    encoding: str
    stamp_ns: int
    frame_id: str = ""


def image_from_fields(*, stamp_ns: int, frame_id: str, encoding: str, width: int, height: int, step: int,
                      is_bigendian: bool, data) -> RosImage:
    """A sensor_msgs/Image's fields -> RosImage; FrameError for unusable images."""
    payload, enc = pack_raw_rows(bytes(data), encoding, int(width), int(height), int(step),
                                 big_endian=bool(is_bigendian))
    return RosImage(payload, enc, stamp_ns, frame_id)


def compressed_from_fields(*, stamp_ns: int, frame_id: str, fmt: str, data) -> RosImage:
    """A sensor_msgs/CompressedImage's fields -> RosImage (the decoder refuses unknown formats)."""
    return RosImage(bytes(data), compressed_format_to_encoding(fmt), stamp_ns, frame_id)


def decode_image_cdr(data: bytes | memoryview) -> RosImage:
    """Decode a CDR ``sensor_msgs/msg/Image``; raises FrameError (reason in BAD_FRAME_REASONS)."""
    r = _Reader(data, IMAGE_TYPE)
    stamp = r.stamp_ns()
    frame_id = r.string("header.frame_id")
    height = r.u32("height")
    width = r.u32("width")
    encoding = r.string("encoding")
    big = r.u8("is_bigendian")
    step = r.u32("step")
    pixels = r.octets("data")
    if big > 1:
        r._fail(f"is_bigendian is {big}, not 0 or 1")
    return image_from_fields(stamp_ns=stamp, frame_id=frame_id, encoding=encoding, width=width, height=height,
                             step=step, is_bigendian=bool(big), data=pixels)


def decode_compressed_cdr(data: bytes | memoryview) -> RosImage:
    """Decode a CDR ``sensor_msgs/msg/CompressedImage``; raises FrameError."""
    r = _Reader(data, COMPRESSED_IMAGE_TYPE)
    stamp = r.stamp_ns()
    frame_id = r.string("header.frame_id")
    fmt = r.string("format")
    pixels = r.octets("data")
    return compressed_from_fields(stamp_ns=stamp, frame_id=frame_id, fmt=fmt, data=pixels)


#: Message type -> CDR decoder, for the image types the runtime reads.
DECODERS = {IMAGE_TYPE: decode_image_cdr, COMPRESSED_IMAGE_TYPE: decode_compressed_cdr}


class _Writer:
    """Little-endian CDR being built; fields aligned to their size from the end of the header."""

    def __init__(self) -> None:
        self.buf = bytearray(b"\x00\x01\x00\x00")

    def _align(self, n: int) -> None:
        self.buf += bytes((-(len(self.buf) - 4)) % n)

    def u8(self, value: int) -> None:
        self.buf += struct.pack("<B", value)

    def u32(self, value: int) -> None:
        self._align(4)
        self.buf += struct.pack("<I", value)

    def i32(self, value: int) -> None:
        self._align(4)
        self.buf += struct.pack("<i", value)

    def string(self, text: str) -> None:
        raw = text.encode("utf-8") + b"\x00"
        self.u32(len(raw))
        self.buf += raw

    def header(self, stamp_ns: int, frame_id: str = "") -> None:
        sec, nanosec = divmod(max(0, stamp_ns), 1_000_000_000)
        self.i32(min(sec, 2**31 - 1))  # builtin_interfaces/Time.sec is an int32
        self.u32(nanosec)
        self.string(frame_id)


def encode_string_cdr(text: str) -> bytes:
    """A ``std_msgs/msg/String`` as little-endian CDR (header, uint32 length with NUL, bytes)."""
    w = _Writer()
    w.string(text)
    return bytes(w.buf)


@dataclass(frozen=True)
class DiagnosticStatus:
    """One diagnostic_msgs/DiagnosticStatus: level (OK 0, WARN 1, ERROR 2, STALE 3), name,
    message, hardware_id and (key, value) string pairs."""

    level: int
    name: str
    message: str
    hardware_id: str
    values: tuple[tuple[str, str], ...] = ()


def encode_diagnostic_array_cdr(stamp_ns: int, statuses: list[DiagnosticStatus] | tuple[DiagnosticStatus, ...],
                                frame_id: str = "") -> bytes:
    """A ``diagnostic_msgs/msg/DiagnosticArray`` as little-endian CDR; stamp_ns: header stamp (ns)."""
    w = _Writer()
    w.header(stamp_ns, frame_id)
    w.u32(len(statuses))
    for status in statuses:
        w.u8(status.level)
        w.string(status.name)
        w.string(status.message)
        w.string(status.hardware_id)
        w.u32(len(status.values))
        for key, value in status.values:
            w.string(key)
            w.string(value)
    return bytes(w.buf)


# ============================================================================ message definitions (MCAP ros2 profile)

_MSGDEF_SEPARATOR = "=" * 80 + "\n"
_HEADER_MSGDEFS = (
    _MSGDEF_SEPARATOR + "MSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\nstring frame_id\n"
    + _MSGDEF_SEPARATOR + "MSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n"
)
#: ROS 2 message definitions (schema encoding ``ros2msg``) as rosbag2 and rosbags write them: the
#: type's fields, then each nested type after a separator line and ``MSG: <type>``.
COMPRESSED_IMAGE_MSGDEF = "std_msgs/Header header\nstring format\nuint8[] data\n" + _HEADER_MSGDEFS
STRING_MSGDEF = "string data\n"
DIAGNOSTIC_ARRAY_MSGDEF = (
    "std_msgs/Header header\ndiagnostic_msgs/DiagnosticStatus[] status\n" + _HEADER_MSGDEFS
    + _MSGDEF_SEPARATOR + "MSG: diagnostic_msgs/DiagnosticStatus\nbyte OK=0\nbyte WARN=1\nbyte ERROR=2\n"
    "byte STALE=3\nbyte level\nstring name\nstring message\nstring hardware_id\ndiagnostic_msgs/KeyValue[] values\n"
    + _MSGDEF_SEPARATOR + "MSG: diagnostic_msgs/KeyValue\nstring key\nstring value\n"
)
#: Message definition of each type the ros2 profile writes.
MSGDEFS = {COMPRESSED_IMAGE_TYPE: COMPRESSED_IMAGE_MSGDEF, STRING_TYPE: STRING_MSGDEF,
           DIAGNOSTIC_ARRAY_TYPE: DIAGNOSTIC_ARRAY_MSGDEF}


def decode_string_cdr(data: bytes | memoryview) -> str:
    """The text of a CDR ``std_msgs/msg/String`` of any length; raises FrameError ``corrupt``."""
    r = _Reader(data, STRING_TYPE)
    raw = bytes(r.octets("data"))
    if not raw or raw[-1] != 0:
        r._fail("data is not NUL-terminated")
    try:
        return raw[:-1].decode("utf-8")
    except UnicodeDecodeError:
        r._fail("data is not UTF-8")
