"""The AE-VQ autoencoders over descriptor vectors: the paper's 1-D conv stack and a light MLP.

arch "paper" (section 3.1): a descriptor vector (D,) is read as a one-channel 1-D signal of length D:

    encoder: scale to [0,1] -> [Conv1d(k3)+BN+ReLU] x2 at width w, MaxPool(2)   for w in widths
             -> flatten -> Linear -> latent code (latent_dim,)
    decoder: Linear -> [Conv1d(k3)+BN+ReLU] x2 at width w, Upsample(2)          for w in reversed(widths)
             -> Conv1d(k3, 1 channel) -> sigmoid

arch "light": scale -> [Linear + ReLU] for w in widths -> Linear -> latent, mirrored decoder
(hundreds of times less arithmetic per descriptor than the conv stack: it converges in minutes
on 2 CPU cores and its int8 graph runs at k-means cost).

trained self-supervised with binary cross-entropy against the [0,1]-scaled input (eq. 1),
optionally plus a matching term (`match_weight`): an InfoNCE loss that pulls the codes of the
two descriptors of a matching pair (same scene point, trainer/aefabmap_trainer/match_pairs.py) together and
pushes the other pairs of the batch away, so both land on the same word more often.
The [0,1] scaling (per-row min-max for SIFT, identity for ORB bits) lives inside the encoder
module, so the exported ONNX graph takes raw descriptor vectors.

Only the encoder is used after training: the vocabulary is built on its codes
(trainer/aefabmap_trainer/latent_vocabulary.py) and exported with it as one graph (export/aefabmap_export/onnx_export.py).
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

from aefabmap_runtime.errors import ConfigError, InputError
from aefabmap_runtime.core.features.feature_kinds import get_kind

SCALINGS = ("minmax", "none")
ARCHS = ("paper", "light")
DEFAULT_WIDTHS = {"paper": (32, 64, 128), "light": (256,)}
# Light arch: a 32-D code keeps the fp32 codebook arg-min of a 2000-word vocabulary within the
# int8 budget of the whole quantiser; 64-D did not (docs/results.md, "Quantiser").
DEFAULT_LIGHT_LATENT = 32


@dataclass(frozen=True)
class AeConfig:
    """Autoencoder architecture and training settings.

    arch: "paper" (1-D conv stack) or "light" (MLP), see the module doc.
    latent_dim: size of the dense bottleneck; None -> paper: D // 2 (64 for SIFT as in the
        authors' notebook, 128 for ORB: the 256 rBRIEF tests were selected to be
        uncorrelated, so there is little redundancy to squeeze and a 64-D code loses
        most of the reconstruction); light: DEFAULT_LIGHT_LATENT.
    widths: None -> DEFAULT_WIDTHS[arch]. paper: conv widths of the encoder stages; each stage
        is a Conv+BN+ReLU pair followed by a 2x max-pool, so D must be divisible by
        2 ** len(widths). light: hidden layer sizes of the MLP.
    scaling: "minmax" (per-row min-max to [0,1]), "none" (input already in [0,1]),
        or None -> the feature kind's `ae_scaling` ("minmax" for SIFT, "none" for ORB bits).
    max_epochs: upper bound on passes over the training split.
    max_descriptors: training vectors are subsampled (seeded) to at most this many.
    batch_size, learning_rate, weight_decay: Adam settings.
    val_fraction: share of the (subsampled) vectors held out for early stopping.
    patience: epochs without a val-loss improvement of at least min_delta before stopping.
    max_seconds: wall-clock training budget; no new epoch starts once it is spent (None: none).
    match_weight: weight of the matching term (0: reconstruction only); needs pairs.
    match_temperature: InfoNCE temperature on squared code distances divided by their batch mean.
    match_batch: matching pairs per training step.
    match_negatives: "batch": a step's pairs are drawn from all training pairs (negatives from
        other images, easy to tell apart); "image": a step takes consecutive pairs of a random
        arrangement of the pair groups, so the negatives mostly share the positive's image
        (hard negatives, as in the held-out batches, which are kept in group order).
    threads: torch intra-op threads (results are reproducible for a fixed value).
    progress: show a tqdm bar (stderr) with the running loss.
    """

    arch: str = "paper"
    latent_dim: int | None = None
    widths: tuple[int, ...] | None = None
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
    max_seconds: float | None = None
    match_weight: float = 0.0
    match_temperature: float = 0.1
    match_batch: int = 256
    match_negatives: str = "batch"

    def __post_init__(self) -> None:
        if self.latent_dim is not None and (not isinstance(self.latent_dim, int) or self.latent_dim < 1):
            raise ConfigError(f"latent_dim must be None or a positive integer, got {self.latent_dim!r}")
        if self.arch not in ARCHS:
            raise ConfigError(f"arch must be one of {ARCHS}, got {self.arch!r}")
        if self.widths is not None and (not self.widths or any((not isinstance(w, int)) or w < 1 for w in self.widths)):
            raise ConfigError(f"widths must be None or a non-empty tuple of positive integers, got {self.widths!r}")
        if self.max_seconds is not None and not (self.max_seconds > 0):
            raise ConfigError(f"max_seconds must be None or > 0, got {self.max_seconds!r}")
        if self.match_negatives not in ("batch", "image"):
            raise ConfigError(f"match_negatives must be 'batch' or 'image', got {self.match_negatives!r}")
        if self.match_weight < 0 or not (self.match_temperature > 0) or self.match_batch < 2:
            raise ConfigError("match_weight must be >= 0, match_temperature > 0 and match_batch >= 2")
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
        widths = tuple(self.widths) if self.widths is not None else DEFAULT_WIDTHS[self.arch]
        factor = 2 ** len(widths)
        if self.arch == "paper" and descriptor_length % factor:
            raise ConfigError(
                f"descriptor length {descriptor_length} is not divisible by 2**len(widths) = {factor}"
            )
        default_latent = descriptor_length // 2 if self.arch == "paper" else DEFAULT_LIGHT_LATENT
        latent = self.latent_dim if self.latent_dim is not None else default_latent
        scaling = self.scaling if self.scaling is not None else kind.ae_scaling
        return AeConfig(**{**asdict(self), "latent_dim": latent, "scaling": scaling, "widths": widths})

    def to_dict(self) -> dict:
        d = asdict(self)
        d["widths"] = None if self.widths is None else list(self.widths)
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


class _ScaledEncoder(nn.Module):
    """What every encoder shares: its sizes and the row scaling to [0, 1] of its input."""

    def __init__(self, descriptor_length: int, latent_dim: int, scaling: str) -> None:
        super().__init__()
        self.descriptor_length = descriptor_length
        self.latent_dim = latent_dim
        self.scale = RowScale(scaling)

    def scaled(self, x: torch.Tensor) -> torch.Tensor:
        """The [0,1]-scaled input (B, D): the reconstruction target."""
        return self.scale(x)


class Encoder(_ScaledEncoder):
    """Raw descriptor vectors (B, D) float32 -> latent codes (B, latent_dim) float32."""

    def __init__(self, descriptor_length: int, latent_dim: int, widths: tuple[int, ...], scaling: str) -> None:
        super().__init__(descriptor_length, latent_dim, scaling)
        layers: list[nn.Module] = []
        c = 1
        for w in widths:
            layers += _conv_pair(c, w)
            layers.append(nn.MaxPool1d(2))
            c = w
        self.features = nn.Sequential(*layers)
        self.reduced_length = descriptor_length // (2 ** len(widths))
        self.fc = nn.Linear(c * self.reduced_length, latent_dim)

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


class LightEncoder(_ScaledEncoder):
    """MLP encoder: raw descriptor vectors (B, D) -> latent codes (B, latent_dim); same interface as Encoder."""

    def __init__(self, descriptor_length: int, latent_dim: int, widths: tuple[int, ...], scaling: str) -> None:
        super().__init__(descriptor_length, latent_dim, scaling)
        layers: list[nn.Module] = []
        c = descriptor_length
        for w in widths:
            layers += [nn.Linear(c, w), nn.ReLU(inplace=True)]
            c = w
        layers.append(nn.Linear(c, latent_dim))
        self.body = nn.Sequential(*layers)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.body(self.scale(x))


class LightDecoder(nn.Module):
    """MLP decoder: latent codes (B, latent_dim) -> reconstruction logits (B, D)."""

    def __init__(self, descriptor_length: int, latent_dim: int, widths: tuple[int, ...]) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        c = latent_dim
        for w in reversed(widths):
            layers += [nn.Linear(c, w), nn.ReLU(inplace=True)]
            c = w
        layers.append(nn.Linear(c, descriptor_length))
        self.body = nn.Sequential(*layers)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        return self.body(z)


class Autoencoder(nn.Module):
    """Encoder + decoder; forward returns reconstruction logits (B, D)."""

    def __init__(self, descriptor_length: int, config: AeConfig) -> None:
        super().__init__()
        if config.latent_dim is None or config.scaling is None or config.widths is None:
            raise ConfigError("Autoencoder needs a resolved AeConfig (call config.resolved(D, kind))")
        widths = tuple(config.widths)
        if config.arch == "light":
            self.encoder = LightEncoder(descriptor_length, config.latent_dim, widths, config.scaling)
            self.decoder = LightDecoder(descriptor_length, config.latent_dim, widths)
        else:
            self.encoder = Encoder(descriptor_length, config.latent_dim, widths, config.scaling)
            self.decoder = Decoder(descriptor_length, config.latent_dim, widths)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.decoder(self.encoder(x))


@dataclass
class TrainResult:
    """What train_autoencoder returns.

    model: the best (lowest val loss) autoencoder, in eval mode.
    config: the resolved AeConfig used.
    history: per epoch {"epoch", "train_loss", "val_loss", "val_recon", "val_match", "seconds"}:
        BCE in nats per element; with a matching term, loss = BCE + match_weight * InfoNCE
        (val_match: InfoNCE on held-out pairs, also reported when match_weight is 0).
    stop_reason: "patience", "budget" or "max_epochs".
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
    stop_reason: str = "max_epochs"
    n_pairs_train: int = 0
    n_pairs_val: int = 0

    def summary(self) -> dict:
        """JSON-able training summary for the bundle manifest (history included: the loss curve; no
        wall-clock times)."""
        train_loss = round(float(self.history[self.best_epoch - 1]["train_loss"]), 6) if self.history else None
        return training_summary(self, "bce" if self.config.match_weight == 0 else "bce+match", train_loss,
                                self.n_pairs_train, self.n_pairs_val)


def training_summary(result, loss: str, train_loss: float | None, n_pairs_train: int, n_pairs_val: int) -> dict:
    """The manifest's training summary keys both AE objectives share, from a result with best_val_loss,
    best_epoch, epochs_run, stop_reason, n_train, n_val, config and history."""
    return {
        "loss": loss,
        "val_loss": round(float(result.best_val_loss), 6),
        "train_loss": train_loss,
        "best_epoch": result.best_epoch,
        "epochs": result.epochs_run,
        "stop_reason": result.stop_reason,
        "n_descriptors": result.n_train + result.n_val,
        "n_train": result.n_train,
        "n_val": result.n_val,
        "n_pairs_train": n_pairs_train,
        "n_pairs_val": n_pairs_val,
        # Progress bars change no weight: a run with them and one without give the same bytes.
        "config": {k: v for k, v in result.config.to_dict().items() if k != "progress"},
        "history": manifest_history(result.history),
    }


def manifest_history(history: list[dict]) -> list[dict]:
    """Per-epoch history as the manifest keeps it: floats rounded, wall-clock "seconds" left out
    (the same command must give the same bundle bytes; the train command prints its timings)."""
    return [{k: (round(v, 6) if isinstance(v, float) else v) for k, v in h.items() if k != "seconds"} for h in history]


def held_out_descriptors(vectors: np.ndarray, cfg: AeConfig, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(train, val) float32 tensors: up to cfg.max_descriptors rows of vectors (N, D) (seeded
    subsample), shuffled, cfg.val_fraction of them (at least one) held out for early stopping."""
    data = subsample(vectors, cfg.max_descriptors, seed)
    perm = np.random.default_rng(seed + 1).permutation(data.shape[0])
    n_val = max(1, int(round(cfg.val_fraction * data.shape[0])))
    return torch.from_numpy(data[perm[n_val:]].copy()), torch.from_numpy(data[perm[:n_val]].copy())


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


def match_loss(za: torch.Tensor, zb: torch.Tensor, temperature: float) -> torch.Tensor:
    """Symmetric InfoNCE on codes za, zb (B, L) of matching pairs (row i of each is one pair).

    Logits are negative squared L2 distances (the quantiser's distance) divided by their batch
    mean (detached, so the term cannot win by shrinking or inflating the code scale) and by
    `temperature`; the positive of row i is column i, the other B - 1 pairs are negatives.
    """
    d2 = torch.cdist(za, zb).pow(2)
    logits = -d2 / (d2.detach().mean().clamp_min(1e-12) * temperature)
    target = torch.arange(za.shape[0])
    return 0.5 * (nn.functional.cross_entropy(logits, target) + nn.functional.cross_entropy(logits.T, target))


def train_autoencoder(
    vectors: np.ndarray,
    *,
    feature_kind: str,
    seed: int = 0,
    config: AeConfig | None = None,
    pairs: tuple[np.ndarray, np.ndarray] | None = None,
    val_pairs: tuple[np.ndarray, np.ndarray] | None = None,
    pair_groups: np.ndarray | None = None,
) -> TrainResult:
    """Train the autoencoder on descriptor vectors (N, D) float32 (training images only).

    pairs / val_pairs: matching descriptor vectors (a (P, D), b (P, D)) for the matching term
    (trained on `pairs`, held-out loss on `val_pairs`); required when config.match_weight > 0.
    pair_groups: (P,) source image of each training pair (needed for match_negatives "image").
    Same inputs, seed and config.threads -> bit-identical weights (unless max_seconds ends the
    run: wall-clock time then decides the number of epochs). Early stopping on a held-out split
    of `vectors` (and `val_pairs`); the best epoch's weights are returned.
    """
    from tqdm import tqdm  # trainer-only dependency

    vectors = _check_train_vectors(vectors)
    d = int(vectors.shape[1])
    cfg = (config or AeConfig()).resolved(d, feature_kind)
    pa, pb = _check_pairs(pairs, d)
    va, vb = _check_pairs(val_pairs, d)
    if cfg.match_weight > 0 and (pa.shape[0] < 2 or va.shape[0] < 2):
        raise InputError("match_weight > 0 needs at least 2 training and 2 held-out matching pairs")
    t0 = time.perf_counter()
    train, val = held_out_descriptors(vectors, cfg, seed)
    n_val = int(val.shape[0])
    pa_t, pb_t = torch.from_numpy(pa), torch.from_numpy(pb)
    if cfg.match_negatives == "image":
        if pair_groups is None or len(pair_groups) != pa.shape[0]:
            raise InputError("match_negatives 'image' needs pair_groups, one per training pair")
        _, group_idx = np.unique(np.asarray(pair_groups), return_inverse=True)
        group_t = torch.from_numpy(group_idx.astype(np.int64))
    va_t, vb_t = torch.from_numpy(va), torch.from_numpy(vb)

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
        stop = "max_epochs"
        for epoch in range(1, cfg.max_epochs + 1):
            if cfg.max_seconds is not None and time.perf_counter() - t0 >= cfg.max_seconds:
                stop = "budget"
                break
            te = time.perf_counter()
            model.train()
            order = torch.randperm(train.shape[0], generator=gen)
            n_batches = math.ceil(train.shape[0] / cfg.batch_size)
            use_pairs = cfg.match_weight > 0
            if use_pairs:
                # Pairs cycle at their own pace: one pair batch per reconstruction batch.
                pair_order = torch.randperm(pa_t.shape[0], generator=gen)
                if cfg.match_negatives == "image":
                    # Random group order, random order inside each group, groups kept together.
                    rank = torch.randperm(int(group_t.max()) + 1, generator=gen).double()
                    pair_order = torch.argsort(rank[group_t] + torch.rand(pa_t.shape[0], generator=gen, dtype=torch.float64))
                n_pb = max(1, pa_t.shape[0] // cfg.match_batch)
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
                if use_pairs:
                    k = b % n_pb
                    j = pair_order[k * cfg.match_batch : (k + 1) * cfg.match_batch]
                    loss = loss + cfg.match_weight * match_loss(
                        model.encoder(pa_t[j]), model.encoder(pb_t[j]), cfg.match_temperature)
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
                total += loss.item() * idx.numel()
                count += idx.numel()
                if b % 20 == 0:
                    bar.set_postfix(loss=f"{total / max(count, 1):.4f}")
            bar.close()
            val_recon = evaluate_loss(model, val, cfg.batch_size * 8)
            val_match = evaluate_match_loss(model, va_t, vb_t, cfg.match_batch, cfg.match_temperature)
            val_loss = val_recon + (cfg.match_weight * val_match if use_pairs else 0.0)
            epochs_run = epoch
            history.append({"epoch": epoch, "train_loss": total / max(count, 1), "val_loss": val_loss,
                            "val_recon": val_recon, "val_match": None if math.isnan(val_match) else val_match,
                            "seconds": round(time.perf_counter() - te, 2)})
            if val_loss < best - cfg.min_delta:
                best, best_epoch, bad = val_loss, epoch, 0
                best_state = copy.deepcopy(model.state_dict())
            else:
                bad += 1
                if bad > cfg.patience:
                    stop = "patience"
                    break
        model.load_state_dict(best_state)
        model.eval()
    return TrainResult(model, cfg, best, best_epoch, epochs_run, int(train.shape[0]), int(n_val),
                       time.perf_counter() - t0, history, stop, int(pa.shape[0]), int(va.shape[0]))


def _check_pairs(pairs, d: int) -> tuple[np.ndarray, np.ndarray]:
    if pairs is None:
        return np.zeros((0, d), np.float32), np.zeros((0, d), np.float32)
    a, b = (np.ascontiguousarray(p, dtype=np.float32) for p in pairs)
    if a.ndim != 2 or a.shape != b.shape or a.shape[1] != d:
        raise InputError(f"matching pairs must be two (P, {d}) arrays, got {a.shape} and {b.shape}")
    if not (np.isfinite(a).all() and np.isfinite(b).all()):
        raise InputError("matching pairs contain NaN or infinite values")
    return a, b


@torch.no_grad()
def evaluate_match_loss(model: Autoencoder, a: torch.Tensor, b: torch.Tensor, batch: int, temperature: float) -> float:
    """Mean matching loss of held-out pairs (a, b) (P, D) in fixed consecutive batches (nan if P < 2)."""
    if a.shape[0] < 2:
        return float("nan")
    was_training = model.training
    model.eval()
    total, n = 0.0, 0
    for s in range(0, a.shape[0], batch):
        if a.shape[0] - s < 2:
            break
        m = min(batch, a.shape[0] - s)
        total += float(match_loss(model.encoder(a[s : s + m]), model.encoder(b[s : s + m]), temperature)) * m
        n += m
    model.train(was_training)
    return total / n


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
