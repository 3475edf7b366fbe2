"""A one-node ONNX graph, Y = A @ W with A uint8 (N, D) and W a constant int8 (D, K), written
as protobuf bytes without the `onnx` package (a board installs the runtime set only).

onnxruntime runs it with its int8 GEMM (AVX2 / AVX-VNNI on x86, NEON dot-product on ARM),
packing W once when the session is built. The bytes follow onnx.proto (IR version 8, opset
13); only the fields this graph needs are written.
"""

from __future__ import annotations

import numpy as np

INPUT_NAME = "bits"
WEIGHT_NAME = "weights"
OUTPUT_NAME = "products"

# onnx.proto TensorProto.DataType values.
_UINT8, _INT8, _INT32 = 2, 3, 6
_IR_VERSION, _OPSET = 8, 13


def _varint(value: int) -> bytes:
    out = bytearray()
    while True:
        byte = value & 0x7F
        value >>= 7
        if value:
            out.append(byte | 0x80)
        else:
            out.append(byte)
            return bytes(out)


def _int_field(number: int, value: int) -> bytes:
    return _varint(number << 3) + _varint(value)


def _bytes_field(number: int, payload: bytes) -> bytes:
    return _varint((number << 3) | 2) + _varint(len(payload)) + payload


def _str_field(number: int, text: str) -> bytes:
    return _bytes_field(number, text.encode())


def _tensor_info(name: str, elem_type: int, dims: tuple[int | str, ...]) -> bytes:
    """ValueInfoProto: name, TypeProto.tensor_type (elem_type, shape); a str dim is symbolic."""
    shape = b"".join(
        _bytes_field(1, _str_field(2, d) if isinstance(d, str) else _int_field(1, d)) for d in dims
    )
    tensor_type = _int_field(1, elem_type) + _bytes_field(2, shape)
    return _str_field(1, name) + _bytes_field(2, _bytes_field(1, tensor_type))


def matmul_integer_model(weights: np.ndarray) -> bytes:
    """Serialised ModelProto of Y[N, K] int32 = MatMulInteger(A[N, D] uint8, weights[D, K] int8)."""
    w = np.ascontiguousarray(weights, dtype=np.int8)
    if w.ndim != 2 or min(w.shape) < 1:
        raise ValueError(f"weights must be a non-empty (D, K) array, got shape {w.shape}")
    d, k = (int(n) for n in w.shape)
    node = (
        _str_field(1, INPUT_NAME) + _str_field(1, WEIGHT_NAME) + _str_field(2, OUTPUT_NAME)
        + _str_field(4, "MatMulInteger")
    )
    initializer = _int_field(1, d) + _int_field(1, k) + _int_field(2, _INT8) + _str_field(8, WEIGHT_NAME)
    initializer += _bytes_field(9, w.tobytes())
    graph = (
        _bytes_field(1, node) + _str_field(2, "bit_products") + _bytes_field(5, initializer)
        + _bytes_field(11, _tensor_info(INPUT_NAME, _UINT8, ("n", d)))
        + _bytes_field(12, _tensor_info(OUTPUT_NAME, _INT32, ("n", k)))
    )
    opset = _str_field(1, "") + _int_field(2, _OPSET)
    return _int_field(1, _IR_VERSION) + _bytes_field(8, opset) + _bytes_field(7, graph)
