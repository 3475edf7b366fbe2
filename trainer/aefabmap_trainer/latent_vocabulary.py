"""The AE-VQ vocabulary: k-means over the autoencoder's latent codes (eq. 3 in latent space).

The word of a descriptor is the nearest codebook entry (squared L2) to its latent code.
Clustering reuses the project's deterministic Lloyd's k-means (trainer/aefabmap_trainer/kmeans.py), so both
vocabularies (raw-descriptor baseline and AE) share one tested implementation.
DEC-style joint refinement is not implemented: plain k-means on the codes is the paper's
eq. (3) reading and keeps the codebook a pure function of (encoder, training codes, seed).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from aefabmap_runtime.errors import ConfigError, InputError
from aefabmap_trainer.autoencoder import Encoder, encode
from aefabmap_trainer.kmeans import KMeansConfig, fit_kmeans


@dataclass
class LatentVocabulary:
    """codebook: (K, latent_dim) float32 word centres in latent space."""

    codebook: np.ndarray
    n_clustered: int

    @property
    def size(self) -> int:
        return int(self.codebook.shape[0])

    def assign(self, codes: np.ndarray, chunk: int = 8192) -> np.ndarray:
        """Word ids (N,) int32 of latent codes (N, latent_dim): argmax(c.z - |c|^2/2) == argmin |z - c|^2."""
        codes = np.ascontiguousarray(codes, dtype=np.float32)
        if codes.ndim != 2 or codes.shape[1] != self.codebook.shape[1]:
            raise InputError(f"codes must have shape (N, {self.codebook.shape[1]}), got {codes.shape}")
        half = 0.5 * np.einsum("kd,kd->k", self.codebook, self.codebook)
        out = np.empty(codes.shape[0], np.int32)
        for s in range(0, codes.shape[0], chunk):
            scores = codes[s : s + chunk] @ self.codebook.T
            scores -= half
            out[s : s + chunk] = np.argmax(scores, axis=1)
        return out


def fit_latent_vocabulary(
    encoder: Encoder,
    vectors: np.ndarray,
    words: int,
    *,
    seed: int = 0,
    max_iterations: int = 25,
    threads: int | None = None,
    progress=None,
) -> LatentVocabulary:
    """Encode descriptor vectors (N, D) and cluster the codes into `words` entries.

    progress: optional callable(iteration, fraction_moved), forwarded to k-means.
    """
    if not isinstance(words, int) or words < 2:
        raise ConfigError(f"vocabulary size must be an integer >= 2, got {words!r}")
    codes = encode(encoder, vectors, threads=threads)
    codebook = fit_kmeans(codes, words, KMeansConfig(max_iterations=max_iterations, seed=seed), progress)
    return LatentVocabulary(np.ascontiguousarray(codebook, dtype=np.float32), int(codes.shape[0]))


# Padding entries of the tree's leaf blocks: a half squared norm no real entry can have, so the
# arg-max never picks them (finite: int8 tooling and ONNX checkers dislike inf initialisers).
PAD_HALF_NORM = np.float32(1e30)


@dataclass
class LatentTree:
    """A two-level latent vocabulary: `branches` coarse centres, each with its own leaf words.

    coarse: (C, L) float32 coarse centres. leaves: (C, M, L) float32 leaf centres, padded to
    M = the largest branch. leaf_half: (C, M) float32 half squared norms (PAD_HALF_NORM at
    padding). ids: (C, M) int64 word id of each leaf (0 at padding). Word of a code = the
    nearest leaf of its nearest coarse centre: ~C + M dot products instead of K.
    """

    coarse: np.ndarray
    leaves: np.ndarray
    leaf_half: np.ndarray
    ids: np.ndarray
    size: int

    def assign(self, codes: np.ndarray) -> np.ndarray:
        """Word ids (N,) int32 of latent codes (N, L), the tree search the ONNX graph runs."""
        codes = np.ascontiguousarray(codes, dtype=np.float32)
        ci = np.argmax(codes @ self.coarse.T - 0.5 * np.einsum("cl,cl->c", self.coarse, self.coarse), axis=1)
        s = np.einsum("nml,nl->nm", self.leaves[ci], codes) - self.leaf_half[ci]
        return self.ids[ci, np.argmax(s, axis=1)].astype(np.int32)


def fit_latent_tree(codes: np.ndarray, words: int, *, branches: int, seed: int = 0,
                    max_iterations: int = 25) -> LatentTree:
    """Cluster latent codes (N, L) into `branches` coarse cells, then each cell's codes into
    leaves in proportion to its share of the codes (at least one each, `words` in total)."""
    codes = np.ascontiguousarray(codes, dtype=np.float32)
    if not isinstance(branches, int) or not (2 <= branches <= words):
        raise ConfigError(f"branches must be an integer in [2, words={words}], got {branches!r}")
    coarse = fit_kmeans(codes, branches, KMeansConfig(max_iterations=max_iterations, seed=seed))
    cell = np.argmax(codes @ coarse.T - 0.5 * np.einsum("cl,cl->c", coarse, coarse), axis=1)
    counts = np.bincount(cell, minlength=branches)
    # Largest-remainder apportionment of `words` leaves over the cells, at least 1 per cell.
    share = counts / counts.sum() * (words - branches)
    k = 1 + np.floor(share).astype(int)
    for i in np.argsort(-(share - np.floor(share)))[: words - int(k.sum())]:
        k[i] += 1
    k = np.minimum(k, np.maximum(counts, 1))  # a cell cannot hold more words than codes
    m, dim = int(k.max()), codes.shape[1]
    leaves = np.zeros((branches, m, dim), np.float32)
    half = np.full((branches, m), PAD_HALF_NORM, np.float32)
    ids = np.zeros((branches, m), np.int64)
    next_id = 0
    for c in range(branches):
        members = codes[cell == c]
        if members.shape[0] == 0:  # empty cell: its coarse centre is its only word
            cent = coarse[c : c + 1]
        elif k[c] == 1 or members.shape[0] <= k[c]:
            cent = members[: k[c]] if members.shape[0] <= k[c] else members.mean(0, keepdims=True)
        else:
            cent = fit_kmeans(members, int(k[c]), KMeansConfig(max_iterations=max_iterations, seed=seed + 1 + c))
        n = cent.shape[0]
        leaves[c, :n] = cent
        half[c, :n] = 0.5 * np.einsum("kd,kd->k", cent, cent)
        ids[c, :n] = np.arange(next_id, next_id + n)
        next_id += n
    return LatentTree(np.ascontiguousarray(coarse, np.float32), leaves, half, ids, next_id)
