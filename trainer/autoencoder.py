"""The paper's 1-D convolutional autoencoder over descriptor vectors (AE-VQ, section 3.1).

A descriptor vector (D,) is read as a one-channel 1-D signal of length D:

    encoder: scale to [0,1] -> [Conv1d(k3)+BN+ReLU] x2 at width w, MaxPool(2)   for w in widths
             -> flatten -> Linear -> latent code (latent_dim,)
    decoder: Linear -> [Conv1d(k3)+BN+ReLU] x2 at width w, Upsample(2)          for w in reversed(widths)
             -> Conv1d(k3, 1 channel) -> sigmoid

trained self-supervised with binary cross-entropy against the [0,1]-scaled input (eq. 1).
The [0,1] scaling (per-row min-max for SIFT, identity for ORB bits) lives inside the encoder
module, so the exported ONNX graph takes raw descriptor vectors.

Only the encoder is used after training: the vocabulary is built on its codes
(trainer/latent_vocabulary.py) and exported with it as one graph (export/onnx_export.py).
"""

from __future__ import annotations

import copy
import math
import time
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field

import numpy as np
import torch
from torch import nn

from aefabmap.errors import ConfigError, InputError
from aefabmap.runtime.core.feature_kinds import get_kind

SCALINGS = ("minmax", "none")


@dataclass(frozen=True)
class AeConfig:
    """Autoencoder architecture and training settings.

    latent_dim: size of the dense bottleneck; None -> D // 2 (64 for SIFT as in the
        authors' notebook, 128 for ORB: the 256 rBRIEF tests were selected to be
        uncorrelated, so there is little redundancy to squeeze and a 64-D code loses
        most of the reconstruction).
    widths: conv widths of the encoder stages; each stage is a Conv+BN+ReLU pair
        followed by a 2x max-pool, so D must be divisible by 2 ** len(widths).
    scaling: "minmax" (per-row min-max to [0,1]), "none" (input already in [0,1]),
        or None -> the feature kind's `ae_scaling` ("minmax" for SIFT, "none" for ORB bits).
    max_epochs: upper bound on passes over the training split.
    max_descriptors: training vectors are subsampled (seeded) to at most this many.
    batch_size, learning_rate, weight_decay: Adam settings.
    val_fraction: share of the (subsampled) vectors held out for early stopping.
    patience: epochs without a val-loss improvement of at least min_delta before stopping.
    threads: torch intra-op threads (results are reproducible for a fixed value).
    progress: show a tqdm bar (stderr) with the running loss.
    """

    latent_dim: int | None = None
    widths: tuple[int, ...] = (32, 64, 128)
    scaling: str | None = None
    max_epochs: int = 3
    max_descriptors: int = 100_000
    batch_size: int = 256
    learning_rate: float = 2e-3
    weight_decay: float = 0.0
    val_fraction: float = 0.05
    patience: int = 2
    min_delta: float = 1e-4
    threads: int = 2
    progress: bool = True

    def __post_init__(self) -> None:
        if self.latent_dim is not None and (not isinstance(self.latent_dim, int) or self.latent_dim < 1):
            raise ConfigError(f"latent_dim must be None or a positive integer, got {self.latent_dim!r}")
        if not self.widths or any((not isinstance(w, int)) or w < 1 for w in self.widths):
            raise ConfigError(f"widths must be a non-empty tuple of positive integers, got {self.widths!r}")
        if self.scaling is not None and self.scaling not in SCALINGS:
            raise ConfigError(f"scaling must be None or one of {SCALINGS}, got {self.scaling!r}")
        for name in ("max_epochs", "max_descriptors", "batch_size", "threads"):
            v = getattr(self, name)
            if not isinstance(v, int) or v < 1:
                raise ConfigError(f"{name} must be a positive integer, got {v!r}")
        if not (0.0 < self.val_fraction < 0.5):
            raise ConfigError(f"val_fraction must be in (0, 0.5), got {self.val_fraction!r}")
        if not (self.learning_rate > 0):
            raise ConfigError(f"learning_rate must be > 0, got {self.learning_rate!r}")
        if self.weight_decay < 0 or self.patience < 0 or self.min_delta < 0:
            raise ConfigError("weight_decay, patience and min_delta must be >= 0")

    def resolved(self, descriptor_length: int, feature_kind: str) -> "AeConfig":
        """Fill the None defaults for a descriptor length / feature kind; checks compatibility."""
        kind = get_kind(feature_kind)  # ConfigError for an unknown kind
        if descriptor_length != kind.vector_length:
            raise ConfigError(f"{kind.name} descriptor vectors have length {kind.vector_length}, got {descriptor_length}")
        factor = 2 ** len(self.widths)
        if descriptor_length % factor:
            raise ConfigError(
                f"descriptor length {descriptor_length} is not divisible by 2**len(widths) = {factor}"
            )
        latent = self.latent_dim if self.latent_dim is not None else descriptor_length // 2
        scaling = self.scaling if self.scaling is not None else kind.ae_scaling
        return AeConfig(**{**asdict(self), "latent_dim": latent, "scaling": scaling, "widths": tuple(self.widths)})

    def to_dict(self) -> dict:
        d = asdict(self)
        d["widths"] = list(self.widths)
        return d


class RowScale(nn.Module):
    """Per-row [0,1] scaling, (B, D) -> (B, D). "minmax": (x - min) / (max - min); "none": identity.

    Constant rows (max == min) map to 0 rather than NaN.
    """

    def __init__(self, mode: str) -> None:
        super().__init__()
        if mode not in SCALINGS:
            raise ConfigError(f"scaling must be one of {SCALINGS}, got {mode!r}")
        self.mode = mode

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.mode == "none":
            return x
        lo = torch.amin(x, dim=1, keepdim=True)
        hi = torch.amax(x, dim=1, keepdim=True)
        return (x - lo) / torch.clamp(hi - lo, min=1e-12)


def _conv_pair(c_in: int, c_out: int) -> list[nn.Module]:
    # bias=False: the BatchNorm shift makes a conv bias redundant.
    return [
        nn.Conv1d(c_in, c_out, 3, padding=1, bias=False),
        nn.BatchNorm1d(c_out),
        nn.ReLU(inplace=True),
        nn.Conv1d(c_out, c_out, 3, padding=1, bias=False),
        nn.BatchNorm1d(c_out),
        nn.ReLU(inplace=True),
    ]


class Encoder(nn.Module):
    """Raw descriptor vectors (B, D) float32 -> latent codes (B, latent_dim) float32."""

    def __init__(self, descriptor_length: int, latent_dim: int, widths: tuple[int, ...], scaling: str) -> None:
        super().__init__()
        self.descriptor_length = descriptor_length
        self.latent_dim = latent_dim
        self.scale = RowScale(scaling)
        layers: list[nn.Module] = []
        c = 1
        for w in widths:
            layers += _conv_pair(c, w)
            layers.append(nn.MaxPool1d(2))
            c = w
        self.features = nn.Sequential(*layers)
        self.reduced_length = descriptor_length // (2 ** len(widths))
        self.fc = nn.Linear(c * self.reduced_length, latent_dim)

    def scaled(self, x: torch.Tensor) -> torch.Tensor:
        """The [0,1]-scaled input (B, D): the reconstruction target."""
        return self.scale(x)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = self.features(self.scale(x).unsqueeze(1))
        return self.fc(torch.flatten(h, 1))


class Decoder(nn.Module):
    """Latent codes (B, latent_dim) -> reconstruction logits (B, D) (sigmoid gives [0,1])."""

    def __init__(self, descriptor_length: int, latent_dim: int, widths: tuple[int, ...]) -> None:
        super().__init__()
        rev = tuple(reversed(widths))
        self.c0 = rev[0]
        self.l0 = descriptor_length // (2 ** len(widths))
        self.fc = nn.Linear(latent_dim, self.c0 * self.l0)
        layers: list[nn.Module] = [nn.ReLU(inplace=True)]
        c = self.c0
        for w in rev:
            layers += _conv_pair(c, w)
            layers.append(nn.Upsample(scale_factor=2, mode="nearest"))
            c = w
        layers.append(nn.Conv1d(c, 1, 3, padding=1))
        self.body = nn.Sequential(*layers)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        h = self.fc(z).view(z.shape[0], self.c0, self.l0)
        return self.body(h).squeeze(1)


class Autoencoder(nn.Module):
    """Encoder + decoder; forward returns reconstruction logits (B, D)."""

    def __init__(self, descriptor_length: int, config: AeConfig) -> None:
        super().__init__()
        if config.latent_dim is None or config.scaling is None:
            raise ConfigError("Autoencoder needs a resolved AeConfig (call config.resolved(D, kind))")
        self.encoder = Encoder(descriptor_length, config.latent_dim, tuple(config.widths), config.scaling)
        self.decoder = Decoder(descriptor_length, config.latent_dim, tuple(config.widths))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.decoder(self.encoder(x))


@dataclass
class TrainResult:
    """What train_autoencoder returns.

    model: the best (lowest val loss) autoencoder, in eval mode.
    config: the resolved AeConfig used.
    history: per epoch {"epoch", "train_loss", "val_loss", "seconds"} (BCE, nats per element).
    """

    model: Autoencoder
    config: AeConfig
    best_val_loss: float
    best_epoch: int
    epochs_run: int
    n_train: int
    n_val: int
    seconds: float
    history: list[dict] = field(default_factory=list)

    def summary(self) -> dict:
        """JSON-able training summary for the bundle manifest."""
        return {
            "loss": "bce",
            "val_loss": round(float(self.best_val_loss), 6),
            "train_loss": round(float(self.history[self.best_epoch - 1]["train_loss"]), 6) if self.history else None,
            "best_epoch": self.best_epoch,
            "epochs": self.epochs_run,
            "n_descriptors": self.n_train + self.n_val,
            "n_train": self.n_train,
            "n_val": self.n_val,
            "seconds": round(self.seconds, 1),
            "config": self.config.to_dict(),
        }


@contextmanager
def deterministic_torch(threads: int):
    """Deterministic algorithms and a fixed thread count inside the block; restores the caller's settings."""
    prev_threads = torch.get_num_threads()
    prev_det = torch.are_deterministic_algorithms_enabled()
    torch.set_num_threads(threads)
    torch.use_deterministic_algorithms(True)
    try:
        yield
    finally:
        torch.use_deterministic_algorithms(prev_det)
        torch.set_num_threads(prev_threads)


def _check_train_vectors(vectors: np.ndarray) -> np.ndarray:
    vectors = np.asarray(vectors)
    if vectors.ndim != 2 or vectors.shape[0] < 20:
        raise InputError(f"need a (N, D) array with N >= 20 training vectors, got shape {vectors.shape}")
    vectors = np.ascontiguousarray(vectors, dtype=np.float32)
    if not np.isfinite(vectors).all():
        raise InputError("training vectors contain NaN or infinite values")
    return vectors


def subsample(vectors: np.ndarray, limit: int, seed: int) -> np.ndarray:
    """At most `limit` rows of (N, D) `vectors`, chosen without replacement by `seed`, original order kept."""
    if vectors.shape[0] <= limit:
        return vectors
    rng = np.random.default_rng(seed)
    idx = np.sort(rng.choice(vectors.shape[0], size=limit, replace=False))
    return vectors[idx]


def train_autoencoder(
    vectors: np.ndarray, *, feature_kind: str, seed: int = 0, config: AeConfig | None = None
) -> TrainResult:
    """Train the autoencoder on descriptor vectors (N, D) float32 (training images only).

    Same inputs, seed and config.threads -> bit-identical weights. Early stopping on a
    held-out split; the best epoch's weights are returned.
    """
    from tqdm import tqdm  # trainer-only dependency

    vectors = _check_train_vectors(vectors)
    d = int(vectors.shape[1])
    cfg = (config or AeConfig()).resolved(d, feature_kind)
    t0 = time.perf_counter()
    data = subsample(vectors, cfg.max_descriptors, seed)
    rng = np.random.default_rng(seed + 1)
    perm = rng.permutation(data.shape[0])
    n_val = max(1, int(round(cfg.val_fraction * data.shape[0])))
    val = torch.from_numpy(data[perm[:n_val]].copy())
    train = torch.from_numpy(data[perm[n_val:]].copy())

    with deterministic_torch(cfg.threads):
        torch.manual_seed(seed)
        model = Autoencoder(d, cfg)
        opt = torch.optim.Adam(model.parameters(), lr=cfg.learning_rate, weight_decay=cfg.weight_decay)
        # BCE on logits == sigmoid output + BCE, but numerically stable.
        loss_fn = nn.BCEWithLogitsLoss()
        gen = torch.Generator().manual_seed(seed)
        best = math.inf
        best_state = copy.deepcopy(model.state_dict())
        best_epoch = 0
        bad = 0
        history: list[dict] = []
        epochs_run = 0
        for epoch in range(1, cfg.max_epochs + 1):
            te = time.perf_counter()
            model.train()
            order = torch.randperm(train.shape[0], generator=gen)
            n_batches = math.ceil(train.shape[0] / cfg.batch_size)
            total, count = 0.0, 0
            bar = tqdm(range(n_batches), desc=f"AE epoch {epoch}/{cfg.max_epochs}", unit="batch",
                       disable=not cfg.progress, leave=False, mininterval=0.5)
            for b in bar:
                idx = order[b * cfg.batch_size : (b + 1) * cfg.batch_size]
                if idx.numel() < 2:  # BatchNorm needs > 1 sample in training mode
                    continue
                x = train[idx]
                target = model.encoder.scaled(x)
                loss = loss_fn(model(x), target)
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
                total += loss.item() * idx.numel()
                count += idx.numel()
                if b % 20 == 0:
                    bar.set_postfix(loss=f"{total / max(count, 1):.4f}")
            bar.close()
            val_loss = evaluate_loss(model, val, cfg.batch_size * 8)
            epochs_run = epoch
            history.append({"epoch": epoch, "train_loss": total / max(count, 1), "val_loss": val_loss,
                            "seconds": round(time.perf_counter() - te, 2)})
            if val_loss < best - cfg.min_delta:
                best, best_epoch, bad = val_loss, epoch, 0
                best_state = copy.deepcopy(model.state_dict())
            else:
                bad += 1
                if bad > cfg.patience:
                    break
        model.load_state_dict(best_state)
        model.eval()
    return TrainResult(model, cfg, best, best_epoch, epochs_run, int(train.shape[0]), int(n_val),
                       time.perf_counter() - t0, history)


@torch.no_grad()
def evaluate_loss(model: Autoencoder, vectors: torch.Tensor, batch: int = 2048) -> float:
    """Mean BCE (per element) of the model's reconstruction of `vectors` (N, D), in eval mode."""
    was_training = model.training
    model.eval()
    loss_fn = nn.BCEWithLogitsLoss(reduction="sum")
    total = 0.0
    for s in range(0, vectors.shape[0], batch):
        x = vectors[s : s + batch]
        total += float(loss_fn(model(x), model.encoder.scaled(x)))
    model.train(was_training)
    return total / (vectors.shape[0] * vectors.shape[1])


@torch.no_grad()
def encode(encoder: Encoder, vectors: np.ndarray, batch: int = 4096, threads: int | None = None) -> np.ndarray:
    """Latent codes (N, latent_dim) float32 of descriptor vectors (N, D), encoder in eval mode."""
    vectors = np.ascontiguousarray(vectors, dtype=np.float32)
    if vectors.ndim != 2 or vectors.shape[1] != encoder.descriptor_length:
        raise InputError(f"vectors must have shape (N, {encoder.descriptor_length}), got {vectors.shape}")
    encoder.eval()
    out = np.empty((vectors.shape[0], encoder.latent_dim), np.float32)
    prev = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(threads)
    try:
        for s in range(0, vectors.shape[0], batch):
            out[s : s + batch] = encoder(torch.from_numpy(vectors[s : s + batch])).numpy()
    finally:
        torch.set_num_threads(prev)
    return out
