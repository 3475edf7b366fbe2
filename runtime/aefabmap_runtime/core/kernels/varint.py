"""Unsigned LEB128 varints, as protobuf and zenoh's serialiser write them."""

from __future__ import annotations


def read_varint(buf, pos: int) -> tuple[int, int]:
    """(value, position after it) of the varint at `pos` of bytes-like `buf`; ValueError when it
    runs past the end or past 64 bits."""
    value = shift = 0
    while pos < len(buf) and shift <= 63:
        b = buf[pos]
        pos += 1
        value |= (b & 0x7F) << shift
        if not b & 0x80:
            return value, pos
        shift += 7
    raise ValueError("truncated varint")
