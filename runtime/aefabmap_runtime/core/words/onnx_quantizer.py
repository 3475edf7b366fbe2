"""The autoencoder quantiser at run time: one onnxruntime call, descriptors in, words out.

Deliberately imports only numpy and onnxruntime (no torch, no onnx), so a board needs the
runtime set only. The graph (written by export/aefabmap_export/onnx_export.py, optionally int8 by
export/aefabmap_export/quantize_int8.py) has:

    input   descriptors  float32 (batch, D)
    output  words        int32 or int64 (batch,)   word id in [0, K)
    output  codes        float32 (batch, latent)
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnxruntime as ort

from aefabmap_runtime.errors import BundleError, ConfigError, InputError
from aefabmap_runtime.core.words.onnx_external import has_external_data
from aefabmap_runtime.core.words.quantizer import check_vectors

INPUT_NAME = "descriptors"
WORDS_NAME = "words"
CODES_NAME = "codes"
#: Synthetic descriptors of each form the load-time probe quantises.
PROBE_ROWS = 64
#: Largest quantiser model read (bytes): the exported graphs are a few MB.
MAX_MODEL_BYTES = 256 * 2**20
_FLOAT = "tensor(float)"
_INTS = ("tensor(int32)", "tensor(int64)")


def session_options(threads: int) -> ort.SessionOptions:
    """onnxruntime options of the runtime's graphs: `threads` intra-op threads, one inter-op
    thread (each graph is a single chain), sequential, all graph optimisations, no warnings."""
    if not isinstance(threads, int) or threads < 1:
        raise ConfigError(f"threads must be a positive integer, got {threads!r}")
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    opts.log_severity_level = 3  # no warnings on stderr from library code
    return opts


class OnnxQuantizer:
    """Quantizer backed by an ONNX graph (Quantizer protocol of runtime/aefabmap_runtime/core/words/quantizer.py).

    model_path: .onnx file (fp32 or QDQ int8).
    vocabulary_size: K expected by the bundle; checked against the codebook inside the graph.
    descriptor_length: D expected by the bundle; checked against the graph's input.
    threads: onnxruntime intra-op threads (inter-op is 1: the graph is a single chain).
    The codebook size K is read from the model metadata key "vocabulary_size" that
    export/aefabmap_export/onnx_export.py writes (K is not visible in the graph's output shapes).
    """

    def __init__(self, model_path: str | Path, *, vocabulary_size: int, descriptor_length: int, threads: int = 1) -> None:
        opts = session_options(threads)
        if not isinstance(vocabulary_size, int) or vocabulary_size < 1:
            raise ConfigError(f"vocabulary_size must be a positive integer, got {vocabulary_size!r}")
        if not isinstance(descriptor_length, int) or descriptor_length < 1:
            raise ConfigError(f"descriptor_length must be a positive integer, got {descriptor_length!r}")
        self.model_path = Path(model_path)
        self.vocabulary_size = vocabulary_size
        self.descriptor_length = descriptor_length
        if not self.model_path.is_file():
            raise BundleError(f"quantiser model {self.model_path} does not exist")
        # On x86 without VNNI, u8 x s8 int8 kernels sum products pairwise in int16 and
        # saturate for 8-bit weights; this makes onnxruntime use exact u8 x u8 kernels there.
        # Graphs from export/aefabmap_export/quantize_int8.py have 7-bit weights, which cannot saturate and
        # run as fast with it; int8 graphs exported before that change are made exact by it.
        opts.add_session_config_entry("session.x64quantprecision", "1")
        # Loaded from the bytes read here, checked to hold every tensor themselves: onnxruntime
        # given a path would also read (and stat) external-data files no checksum covers.
        try:
            with open(self.model_path, "rb") as fh:
                model = fh.read(MAX_MODEL_BYTES + 1)
        except OSError as exc:
            raise BundleError(f"cannot read quantiser model {self.model_path}: {exc.strerror or exc}") from exc
        if len(model) > MAX_MODEL_BYTES:
            raise BundleError(f"quantiser model {self.model_path} is larger than {MAX_MODEL_BYTES} bytes")
        try:
            external = has_external_data(model)
        except BundleError as exc:
            raise BundleError(f"cannot load quantiser model {self.model_path}: {exc}") from exc
        if external:
            raise BundleError(f"quantiser model {self.model_path} keeps tensor data in other files (external data): "
                              "a bundle's model must hold all its weights")
        try:
            self._session = ort.InferenceSession(model, sess_options=opts, providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime raises its own (non-exported) exception types
            raise BundleError(f"cannot load quantiser model {self.model_path}: {exc}") from exc
        self.latent_dim = self._validate()
        self._empty_codes = np.zeros((0, self.latent_dim), np.float32)
        self._probe()

    def _probe(self) -> None:
        """Run the graph once on synthetic descriptors (binary-like bit vectors and unit float
        vectors): a model whose word ids fall outside the vocabulary is refused at load
        (BundleError), not on a running node's first frame."""
        rng = np.random.default_rng(0)
        bits = rng.integers(0, 2, (PROBE_ROWS, self.descriptor_length)).astype(np.float32)
        floats = rng.random((PROBE_ROWS, self.descriptor_length)).astype(np.float32)
        floats /= np.linalg.norm(floats, axis=1, keepdims=True)
        self.quantize(np.vstack([bits, floats]))

    def _validate(self) -> int:
        """Check names, dtypes and static shapes of the graph; returns the latent size."""
        s, p = self._session, self.model_path
        inputs = s.get_inputs()
        if len(inputs) != 1 or inputs[0].name != INPUT_NAME:
            raise BundleError(f"{p}: expected one input {INPUT_NAME!r}, found {[i.name for i in inputs]}")
        inp = inputs[0]
        if inp.type != _FLOAT or len(inp.shape) != 2:
            raise BundleError(f"{p}: input {INPUT_NAME!r} must be float32 (batch, D), is {inp.type} {inp.shape}")
        if inp.shape[1] != self.descriptor_length:
            raise BundleError(
                f"{p}: model takes descriptors of length {inp.shape[1]}, bundle expects {self.descriptor_length}"
            )
        outputs = {o.name: o for o in s.get_outputs()}
        if WORDS_NAME not in outputs or CODES_NAME not in outputs:
            raise BundleError(f"{p}: expected outputs {WORDS_NAME!r} and {CODES_NAME!r}, found {sorted(outputs)}")
        words, codes = outputs[WORDS_NAME], outputs[CODES_NAME]
        if words.type not in _INTS or len(words.shape) != 1:
            raise BundleError(f"{p}: output {WORDS_NAME!r} must be int32/int64 (batch,), is {words.type} {words.shape}")
        if codes.type != _FLOAT or len(codes.shape) != 2 or not isinstance(codes.shape[1], int):
            raise BundleError(f"{p}: output {CODES_NAME!r} must be float32 (batch, latent), is {codes.type} {codes.shape}")
        # K is not part of any output shape: the exporter records it in the model metadata.
        k = self._codebook_size()
        if k != self.vocabulary_size:
            raise BundleError(f"{p}: model has a codebook of {k} words, bundle expects {self.vocabulary_size}")
        return int(codes.shape[1])

    def _codebook_size(self) -> int:
        meta = self._session.get_modelmeta().custom_metadata_map
        try:
            return int(meta["vocabulary_size"])
        except (KeyError, ValueError) as exc:
            raise BundleError(
                f"{self.model_path}: model metadata lacks 'vocabulary_size' (not written by aefabmap's exporter?)"
            ) from exc

    def quantize(self, vectors: np.ndarray) -> np.ndarray:
        """Word ids (N,) int32 of descriptor vectors (N, D) float32; N may be 0."""
        x = check_vectors(vectors, self.descriptor_length)
        if x.shape[0] == 0:
            return np.zeros(0, np.int32)
        return self._checked_words(self._run([WORDS_NAME], x)[0], x.shape[0])

    def encode(self, vectors: np.ndarray) -> np.ndarray:
        """Latent codes (N, latent_dim) float32 of descriptor vectors (N, D); N may be 0."""
        x = check_vectors(vectors, self.descriptor_length)
        if x.shape[0] == 0:
            return self._empty_codes.copy()
        return np.asarray(self._run([CODES_NAME], x)[0], dtype=np.float32)

    def quantize_and_encode(self, vectors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Both outputs of one run: (words (N,) int32, codes (N, latent) float32)."""
        x = check_vectors(vectors, self.descriptor_length)
        if x.shape[0] == 0:
            return np.zeros(0, np.int32), self._empty_codes.copy()
        words, codes = self._run([WORDS_NAME, CODES_NAME], x)
        return self._checked_words(words, x.shape[0]), np.asarray(codes, dtype=np.float32)

    def _checked_words(self, words: np.ndarray, n: int) -> np.ndarray:
        """The graph's word ids as int32 (n,); BundleError when it gives a wrong count or ids
        outside [0, K): a hostile or broken model must not index outside the vocabulary."""
        w = np.asarray(words).reshape(-1)
        if w.shape[0] != n:
            raise BundleError(f"{self.model_path}: model returned {w.shape[0]} word ids for {n} descriptors")
        if n and (int(w.min()) < 0 or int(w.max()) >= self.vocabulary_size):
            raise BundleError(
                f"{self.model_path}: model returned word ids outside [0, {self.vocabulary_size}) "
                f"(min {int(w.min())}, max {int(w.max())})"
            )
        return w.astype(np.int32)

    def _run(self, names: list[str], x: np.ndarray) -> list[np.ndarray]:
        if not np.isfinite(x).all():
            raise InputError("descriptor vectors contain NaN or infinite values")
        try:
            return self._session.run(names, {INPUT_NAME: x})
        except Exception as exc:
            raise BundleError(f"{self.model_path}: inference failed: {exc}") from exc
