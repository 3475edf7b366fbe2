"""Does an ONNX model keep tensor data outside its own bytes? (Protobuf wire format, no onnx package.)

A bundle's checksums cover the files its manifest names; a tensor whose data lives in another
file ("external data") would be loaded unhashed, from wherever its location points. The walk
follows onnx.proto's messages that can hold tensors: model -> graph / functions -> nodes ->
attributes -> tensors, subgraphs and sparse tensors.
"""

from __future__ import annotations

from aefabmap_runtime.errors import BundleError
from aefabmap_runtime.core.kernels.varint import read_varint

# (message, field number) -> message type of that length-delimited field (onnx.proto).
_CHILDREN = {
    ("model", 7): "graph", ("model", 25): "function",
    ("function", 7): "node",
    ("graph", 1): "node", ("graph", 5): "tensor", ("graph", 15): "sparse",
    ("node", 5): "attribute",
    ("attribute", 5): "tensor", ("attribute", 6): "graph", ("attribute", 10): "tensor",
    ("attribute", 11): "graph", ("attribute", 22): "sparse", ("attribute", 23): "sparse",
    ("sparse", 1): "tensor", ("sparse", 2): "tensor",
}
_TENSOR_EXTERNAL_DATA, _TENSOR_DATA_LOCATION, _EXTERNAL = 13, 14, 1
#: Deepest nesting followed (subgraphs of subgraphs...); deeper is refused, not recursed into.
MAX_DEPTH = 64


def _varint(buf: memoryview, pos: int) -> tuple[int, int]:
    try:
        return read_varint(buf, pos)
    except ValueError:
        raise BundleError("ONNX model is truncated or malformed (varint)") from None


def _walk(buf: memoryview, kind: str, depth: int) -> bool:
    """True when a tensor in this message (of type `kind`) or below keeps external data."""
    if depth > MAX_DEPTH:
        raise BundleError(f"ONNX model nests messages deeper than {MAX_DEPTH}")
    pos = 0
    while pos < len(buf):
        key, pos = _varint(buf, pos)
        field, wire = key >> 3, key & 7
        if wire == 0:
            value, pos = _varint(buf, pos)
            if kind == "tensor" and field == _TENSOR_DATA_LOCATION and value == _EXTERNAL:
                return True
        elif wire == 1:
            pos += 8
        elif wire == 5:
            pos += 4
        elif wire == 2:
            size, pos = _varint(buf, pos)
            if pos + size > len(buf):
                raise BundleError("ONNX model is truncated or malformed (field past its end)")
            if kind == "tensor" and field == _TENSOR_EXTERNAL_DATA:
                return True
            child = _CHILDREN.get((kind, field))
            if child is not None and _walk(buf[pos:pos + size], child, depth + 1):
                return True
            pos += size
        else:
            raise BundleError(f"ONNX model is malformed (wire type {wire})")
    if pos != len(buf):
        raise BundleError("ONNX model is truncated or malformed (field past its end)")
    return False


def has_external_data(model: bytes) -> bool:
    """Whether any tensor of the serialised ModelProto `model` refers to data outside it.
    Raises BundleError for bytes that are not a well-formed protobuf message."""
    return _walk(memoryview(model), "model", 0)
