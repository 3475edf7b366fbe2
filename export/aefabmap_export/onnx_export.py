"""Export encoder + latent codebook arg-min as ONE ONNX graph (trainer side: needs torch and onnx).

Graph contract (checked by runtime/aefabmap_runtime/core/words/onnx_quantizer.py):
    input   descriptors  float32 (batch, D)        raw descriptor vectors, dynamic batch
    output  words        int32   (batch,)          nearest codebook entry in latent space
    output  codes        float32 (batch, latent)   encoder output
"""

from __future__ import annotations

import copy
import logging
import math
import warnings
from pathlib import Path

import numpy as np
import torch
from torch import nn

from aefabmap_runtime.errors import BundleError, InputError

INPUT_NAME = "descriptors"
OUTPUT_NAMES = ("words", "codes")
OPSET = 18
# Fixed producer metadata: the exported bytes depend only on weights and codebook.
PRODUCER = "aefabmap"


def argmax_block(words: int) -> int:
    """Block length of the two-stage arg-max over `words` codebook scores: ~sqrt(K), so that
    both arg-max passes are short, rounded up to 16 (one AVX-512 register of float32)."""
    return 16 * max(1, math.ceil(math.sqrt(words) / 16))


class QuantizerGraph(nn.Module):
    """descriptors (B, D) -> (words (B,) int32, codes (B, latent) float32); encoder: the trainer's
    Encoder (any module with `latent_dim` that maps (B, D) to (B, latent))."""

    def __init__(self, encoder: nn.Module, codebook: np.ndarray) -> None:
        super().__init__()
        codebook = np.ascontiguousarray(codebook, dtype=np.float32)
        if codebook.ndim != 2 or codebook.shape[1] != encoder.latent_dim or codebook.shape[0] < 1:
            raise InputError(f"codebook must have shape (K, {encoder.latent_dim}), got {codebook.shape}")
        self.encoder = copy.deepcopy(encoder).eval()
        self.words = codebook.shape[0]
        self.block = argmax_block(self.words)
        padded = self.block * math.ceil(self.words / self.block)
        # argmin |z - c|^2 == argmax (z.c - |c|^2 / 2): one product, no (B, K, latent) tensor,
        # with -|c|^2 / 2 as the product's bias (one Gemm: no second pass over the B x K scores).
        # The codebook is padded to whole blocks with zero codewords of bias -inf: never chosen.
        codebook_t = np.zeros((codebook.shape[1], padded), np.float32)
        codebook_t[:, : self.words] = codebook.T
        bias = np.full(padded, -np.inf, np.float32)
        bias[: self.words] = -0.5 * np.einsum("kd,kd->k", codebook, codebook)
        self.register_buffer("codebook_t", torch.from_numpy(codebook_t))
        self.register_buffer("neg_half_sq_norms", torch.from_numpy(bias))

    def _padded_scores(self, codes: torch.Tensor) -> torch.Tensor:
        """Latent scores (B, padded K) of codes (B, latent): larger is nearer; padding -inf."""
        return torch.addmm(self.neg_half_sq_norms, codes, self.codebook_t)

    def scores(self, codes: torch.Tensor) -> torch.Tensor:
        """Latent scores (B, K) of codes (B, latent): larger is nearer; padding excluded."""
        return self._padded_scores(codes)[:, : self.words]

    def forward(self, descriptors: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        codes = self.encoder(descriptors)
        scores = self._padded_scores(codes)
        # Arg-max in two stages, the first index of the maximum as one flat arg-max would give:
        # the first block holding the row's maximum (block maxima are one vectorised reduction),
        # then the first maximum inside it. onnxruntime's ArgMax is scalar: over all B x K
        # scores it cost as much as the product itself.
        blocks = scores.view(-1, scores.shape[1] // self.block, self.block)
        best_block = blocks.amax(dim=2).argmax(dim=1, keepdim=True)
        inside = torch.gather(blocks, 1, best_block.unsqueeze(2).expand(-1, -1, self.block)).squeeze(1)
        words = best_block.squeeze(1) * self.block + inside.argmax(dim=1)
        return words.to(torch.int32), codes


def export_quantizer_onnx(encoder: nn.Module, codebook: np.ndarray, path: str | Path) -> Path:
    """Write the fp32 quantiser graph to `path` (single file, weights inside) and check it.

    Returns the path. Raises BundleError when the exported model fails onnx.checker.
    """
    import onnx

    path = Path(path)
    graph = QuantizerGraph(encoder, codebook).eval()
    example = torch.zeros(4, encoder.descriptor_length, dtype=torch.float32)
    example[:, ::3] = 1.0  # non-constant rows: keep min-max scaling away from its 0/0 guard
    # The exporter logs registry notes (e.g. "torchvision is not installed") and deprecation
    # warnings that are no concern of the caller: silence them for the call only.
    logger = logging.getLogger("torch.onnx")
    level = logger.level
    logger.setLevel(logging.ERROR)
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            program = _export(graph, example)
        finally:
            logger.setLevel(level)
    model = program.model_proto
    _normalise(model)
    set_metadata(model, vocabulary_size=int(np.asarray(codebook).shape[0]),
                 descriptor_length=encoder.descriptor_length, latent_dim=encoder.latent_dim)
    try:
        onnx.checker.check_model(model, full_check=True)
    except Exception as exc:  # onnx raises several checker/inference error types
        raise BundleError(f"exported quantiser graph fails the ONNX checker: {exc}") from exc
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(model.SerializeToString(deterministic=True))
    return path


def _export(graph: nn.Module, example: torch.Tensor):
    return torch.onnx.export(
        graph,
        (example,),
        None,
        input_names=[INPUT_NAME],
        output_names=list(OUTPUT_NAMES),
        opset_version=OPSET,
        dynamo=True,
        external_data=False,
        dynamic_shapes={"descriptors": {0: torch.export.Dim("batch")}},
        optimize=True,
        verbose=False,
    )


def set_metadata(model, **values) -> None:
    """Replace the model's metadata_props with `values` (sorted keys; read by the runtime)."""
    del model.metadata_props[:]
    for key in sorted(values):
        entry = model.metadata_props.add()
        entry.key, entry.value = key, str(values[key])


def _normalise(model) -> None:
    """Strip exporter-version metadata and name the batch axis, so bytes depend on weights only."""
    model.producer_name = PRODUCER
    model.producer_version = ""
    model.doc_string = ""
    del model.metadata_props[:]
    model.graph.doc_string = ""
    for node in model.graph.node:
        node.doc_string = ""
        del node.metadata_props[:]
    g = model.graph
    for vi in list(g.input) + list(g.output) + list(g.value_info) + list(g.initializer):
        vi.doc_string = ""
        del vi.metadata_props[:]
    for vi in list(g.input) + list(g.output):
        dims = vi.type.tensor_type.shape.dim
        if len(dims) and not dims[0].HasField("dim_value"):
            dims[0].dim_param = "batch"


def attach_tree_search(model, tree) -> None:
    """Replace the flat codebook arg-min of a quantiser graph (fp32 or int8 ModelProto) by the
    two-level search of a trainer.latent_vocabulary.LatentTree, in place; sets vocabulary_size.

    codes -> coarse arg-max -> Gather the cell's leaf block (B, M, L) -> batched dot products ->
    arg-max -> Gather the leaf's word id. The encoder part (and its int8 Q/DQ) is untouched.
    """
    from onnx import TensorProto, helper, numpy_helper

    g = model.graph
    codes = OUTPUT_NAMES[1]
    nodes = list(g.node)
    downstream: set[int] = set()  # indices: protobuf wrappers have no stable identity
    frontier = {codes}
    changed = True
    while changed:  # every node that (transitively) consumes `codes`: the old arg-min
        changed = False
        for i, node in enumerate(nodes):
            if i not in downstream and any(x in frontier for x in node.input):
                downstream.add(i)
                frontier.update(node.output)
                changed = True
    keep = [copy.deepcopy(n) for i, n in enumerate(nodes) if i not in downstream]
    used = {i for n in keep for i in n.input}
    inits = [t for t in g.initializer if t.name in used]
    del g.node[:]
    g.node.extend(keep)
    del g.initializer[:]
    g.initializer.extend(inits)
    coarse = np.ascontiguousarray(tree.coarse.T, np.float32)
    arrays = {
        "tree_coarse_t": coarse,
        "tree_coarse_half": (0.5 * np.einsum("lc,lc->c", coarse, coarse)).astype(np.float32),
        "tree_leaves": tree.leaves.astype(np.float32),
        "tree_leaf_half": tree.leaf_half.astype(np.float32),
        "tree_ids": tree.ids.astype(np.int64),
        "tree_axes2": np.array([2], np.int64),
        "tree_axes1": np.array([1], np.int64),
    }
    g.initializer.extend(numpy_helper.from_array(a, n) for n, a in arrays.items())
    mk = helper.make_node
    g.node.extend([
        mk("MatMul", [codes, "tree_coarse_t"], ["tree_cs"], name="tree_coarse_mm"),
        mk("Sub", ["tree_cs", "tree_coarse_half"], ["tree_cd"], name="tree_coarse_sub"),
        mk("ArgMax", ["tree_cd"], ["tree_ci"], name="tree_coarse_argmax", axis=1, keepdims=0),
        mk("Gather", ["tree_leaves", "tree_ci"], ["tree_w"], name="tree_gather_leaves", axis=0),
        mk("Unsqueeze", [codes, "tree_axes2"], ["tree_z"], name="tree_unsqueeze"),
        mk("MatMul", ["tree_w", "tree_z"], ["tree_s3"], name="tree_leaf_mm"),
        mk("Squeeze", ["tree_s3", "tree_axes2"], ["tree_s"], name="tree_squeeze"),
        mk("Gather", ["tree_leaf_half", "tree_ci"], ["tree_h"], name="tree_gather_half", axis=0),
        mk("Sub", ["tree_s", "tree_h"], ["tree_d"], name="tree_leaf_sub"),
        mk("ArgMax", ["tree_d"], ["tree_j"], name="tree_leaf_argmax", axis=1, keepdims=1),
        mk("Gather", ["tree_ids", "tree_ci"], ["tree_cell_ids"], name="tree_gather_ids", axis=0),
        mk("GatherElements", ["tree_cell_ids", "tree_j"], ["tree_word2"], name="tree_pick", axis=1),
        mk("Squeeze", ["tree_word2", "tree_axes1"], ["tree_word64"], name="tree_squeeze_word"),
        mk("Cast", ["tree_word64"], [OUTPUT_NAMES[0]], name="tree_cast", to=TensorProto.INT32),
    ])
    meta = {p.key: p.value for p in model.metadata_props}
    meta["vocabulary_size"] = str(tree.size)
    meta["search"] = f"tree:{tree.coarse.shape[0]}x{tree.leaves.shape[1]}"
    set_metadata(model, **meta)
