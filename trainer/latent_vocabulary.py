"""The AE-VQ vocabulary: k-means over the autoencoder's latent codes (eq. 3 in latent space).

The word of a descriptor is the nearest codebook entry (squared L2) to its latent code.
Clustering reuses the project's deterministic Lloyd's k-means (trainer/kmeans.py), so both
vocabularies (raw-descriptor baseline and AE) share one tested implementation.
DEC-style joint refinement is not implemented: plain k-means on the codes is the paper's
eq. (3) reading and keeps the codebook a pure function of (encoder, training codes, seed).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from aefabmap.errors import ConfigError, InputError
from aefabmap.trainer.autoencoder import Encoder, encode
from aefabmap.trainer.kmeans import KMeansConfig, fit_kmeans


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
