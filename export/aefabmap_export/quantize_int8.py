"""Static QDQ int8 quantisation of the quantiser graph (trainer side: needs onnx + onnxruntime).

Only the encoder's Conv/Gemm layers are quantised (per-channel int8 weights, QUInt8
activations, calibrated on training descriptors). The codebook part (MatMul, Sub, ArgMax,
Cast) stays fp32 and the encoder output `codes` is not fake-quantised: an 8-bit code would
move many descriptors across Voronoi borders of a 2000-word codebook, whereas the
conv stack tolerates 8 bits well (see int8 agreement in the manifest). Dynamic int8 is
deliberately not offered: ConvInteger ran slower than fp32 on these CPUs.

Weights use 7 bits ([-64, 64], onnxruntime's reduce_range). On x86 CPUs without VNNI
(e.g. AVX2 only) onnxruntime's u8 x s8 kernels add products pairwise in int16 with
saturation: 2 * 255 * 127 = 64770 overflows 32767, while 2 * 255 * 64 = 32640 cannot.
With full 8-bit weights the fused int8 kernels silently disagree with the graph's own
QDQ arithmetic wherever two neighbouring activations are large -- always so for ORB,
whose 0/1 bits quantise to 0/255 (on an AVX2 machine most ORB words then differed from
fp32). 7-bit weights barely move agreement in exact QDQ arithmetic and make the int8 kernels
compute what the graph says, on every CPU: words equal to fp32 on held-out descriptors rose
for both kinds, at the same speed (docs/results.md, "Autoencoder vs k-means").
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from aefabmap_runtime.errors import BundleError, ConfigError, InputError

# Encoder layers worth quantising; everything else runs in fp32.
QUANTISED_OP_TYPES = ("Conv", "Gemm", "MatMul", "MaxPool", "Relu")


class DescriptorCalibrationReader:
    """onnxruntime CalibrationDataReader over (N, D) float32 descriptor vectors in fixed batches."""

    def __init__(self, vectors: np.ndarray, input_name: str = "descriptors", batch: int = 512) -> None:
        vectors = np.ascontiguousarray(vectors, dtype=np.float32)
        if vectors.ndim != 2 or vectors.shape[0] == 0:
            raise InputError(f"calibration vectors must be a non-empty (N, D) array, got {vectors.shape}")
        # Equal-sized batches: the histogram calibrators stack per-batch outputs into one array.
        usable = (vectors.shape[0] // batch) * batch or vectors.shape[0]
        step = batch if usable >= batch else usable
        self._batches = [vectors[s : s + step] for s in range(0, usable, step)]
        self._name = input_name
        self._i = 0

    def get_next(self) -> dict | None:
        if self._i >= len(self._batches):
            return None
        self._i += 1
        return {self._name: self._batches[self._i - 1]}

    def rewind(self) -> None:
        self._i = 0


def quantize_int8(
    fp32_path: str | Path,
    int8_path: str | Path,
    calibration_vectors: np.ndarray,
    *,
    max_calibration: int = 20_000,
    seed: int = 0,
    calibration: str = "minmax",
) -> Path:
    """Write a static QDQ int8 version of the fp32 quantiser graph at `fp32_path` to `int8_path`.

    calibration_vectors: (N, D) float32 training descriptors; at most max_calibration rows
    (seeded subsample) are run through the model to fix activation ranges.
    calibration: "minmax" | "percentile" (99.999th) | "entropy": how ranges are chosen.
    """
    import onnx
    from onnxruntime.quantization import (
        CalibrationDataReader,
        CalibrationMethod,
        QuantFormat,
        QuantType,
        quantize_static,
    )
    from onnxruntime.quantization.shape_inference import quant_pre_process

    methods = {"minmax": CalibrationMethod.MinMax, "percentile": CalibrationMethod.Percentile,
               "entropy": CalibrationMethod.Entropy}
    if calibration not in methods:
        raise ConfigError(f"calibration must be one of {sorted(methods)}, got {calibration!r}")

    fp32_path, int8_path = Path(fp32_path), Path(int8_path)
    try:
        model = onnx.load(str(fp32_path))
    except Exception as exc:
        raise BundleError(f"cannot read ONNX model {fp32_path}: {exc}") from exc
    vectors = np.asarray(calibration_vectors, dtype=np.float32)
    if vectors.ndim != 2 or vectors.shape[0] == 0:
        raise InputError(f"calibration vectors must be a non-empty (N, D) array, got {vectors.shape}")
    if vectors.shape[0] > max_calibration:
        rng = np.random.default_rng(seed)
        vectors = vectors[np.sort(rng.choice(vectors.shape[0], max_calibration, replace=False))]
    input_name = model.graph.input[0].name

    class _Reader(DescriptorCalibrationReader, CalibrationDataReader):
        pass

    with tempfile.TemporaryDirectory() as tmp:
        pre = Path(tmp) / "pre.onnx"
        # ONNX shape inference + basic ORT graph optimisation before inserting Q/DQ pairs.
        # Symbolic shape inference is skipped: it crashes on the exporter's graph and the
        # static per-tensor shapes from ONNX inference are all the quantiser needs.
        quant_pre_process(str(fp32_path), str(pre), skip_symbolic_shape=True)
        pre_model = onnx.load(str(pre))
        codes_name = "codes"
        # Keep the codebook search in fp32: every node downstream of `codes`.
        exclude = _downstream_nodes(pre_model, codes_name)
        out_tmp = Path(tmp) / "int8.onnx"
        quantize_static(
            str(pre),
            str(out_tmp),
            _Reader(vectors, input_name),
            quant_format=QuantFormat.QDQ,
            op_types_to_quantize=list(QUANTISED_OP_TYPES),
            per_channel=True,
            reduce_range=True,  # 7-bit weights: no int16 saturation on non-VNNI x86 (module doc)
            activation_type=QuantType.QUInt8,
            weight_type=QuantType.QInt8,
            nodes_to_exclude=exclude,
            calibrate_method=methods[calibration],
            extra_options={
                # The bottleneck Gemm's output is the `codes` output: keep it float.
                "OpTypesToExcludeOutputQuantization": ["Gemm"],
            },
            calibration_cache_path=None,
        )
        q = onnx.load(str(out_tmp))
    keep = {e.key: e.value for e in model.metadata_props}
    _strip_metadata(q)
    for key in sorted(keep):  # vocabulary_size etc., which the runtime validates
        entry = q.metadata_props.add()
        entry.key, entry.value = key, keep[key]
    try:
        onnx.checker.check_model(q)
    except Exception as exc:
        raise BundleError(f"int8 quantiser graph fails the ONNX checker: {exc}") from exc
    int8_path.parent.mkdir(parents=True, exist_ok=True)
    int8_path.write_bytes(q.SerializeToString(deterministic=True))
    return int8_path


def _downstream_nodes(model, tensor: str) -> list[str]:
    """Names of the nodes that (transitively) consume `tensor`."""
    frontier, seen, names = {tensor}, set(), []
    changed = True
    while changed:
        changed = False
        for node in model.graph.node:
            if node.name in seen:
                continue
            if any(i in frontier for i in node.input):
                seen.add(node.name)
                names.append(node.name)
                frontier.update(node.output)
                changed = True
    return names


def _strip_metadata(model) -> None:
    """Drop tool-version and temp-path metadata so the bytes depend on weights and calibration only."""
    model.producer_name = "aefabmap"
    model.producer_version = ""
    model.doc_string = ""
    del model.metadata_props[:]
    for node in model.graph.node:
        node.doc_string = ""
