"""The word-assignment objective (`--ae-objective assign`): train the light encoder AND its K words
so that the views of one scene point land on one word.

For latent codes z (N, L) and codebook C (K, L), the soft assignment is

    p(k | z) = softmax_k( -|z - c_k|^2 / (tau * s) )

with s the codebook's mean squared nearest-neighbour spacing (detached, updated with the words'
refreshes, so tau is unitless and the loss cannot win by rescaling codes and words) and tau annealed
geometrically from `temperature_start` to `temperature_end` over `anneal_epochs` epochs. The
hard word (tau -> 0) is the arg-min the exported graph computes, so the trained codebook is the
bundle's vocabulary as it stands (no k-means on the codes afterwards). The words start as
k-means of the initial codes and follow the codes as online k-means (decayed means of the codes
nearest to each word, every step), so the K words always partition the code distribution
whatever its scale: the encoder cannot make views agree by shrinking the codes, only by
bringing views of one point nearer than the words are to each other.

loss = consistency + balance_weight * balance + decorrelation_weight * decorrelation
(+ recon_weight * BCE reconstruction):
- consistency: over every pair (v, w) of views of a track (trainer/aefabmap_trainer/multiview.py, >= 3 views),
  -log sum_k p(k | z_v) p(k | z_w): minus the log probability that the two views draw one word;
- balance: log K - H(word usage): without it one word for everything would be perfectly
  consistent; it keeps the K words in use (as k-means' cells are). Trained against a running
  usage over many batches (running_balance_loss), evaluated on all held-out views;
- decorrelation: squared correlations between code dimensions (codes are standardised per
  dimension, StandardizedEncoder): pulling views together must not fold all dimensions into one.
The loss trains the encoder (and the words with codebook_update "gradient"). Every
`refresh_every` steps the words also take one Lloyd iteration on the current codes of a fixed
sample of training descriptors (empty words re-seeded as trainer/aefabmap_trainer/kmeans.py does). Early stopping
on held-out tracks (whole source images), with the loss evaluated at temperature_end; the
patience count starts once annealing is over; epoch 0 (the initial encoder and words) is a
candidate like any epoch.
"""

from __future__ import annotations

import copy
import math
import time
from dataclasses import asdict, dataclass, field

import numpy as np
import torch
from torch import nn

from aefabmap_runtime.errors import ConfigError, InputError
from aefabmap_trainer.autoencoder import (
    AeConfig,
    Autoencoder,
    _check_train_vectors,
    deterministic_torch,
    evaluate_loss,
    held_out_descriptors,
    training_summary,
)
from aefabmap_trainer.kmeans import KMeansConfig, fit_kmeans
from aefabmap_trainer.multiview import Tracks


#: Starts of the assign objective (AssignConfig.init).
ASSIGN_INITS = ("random", "kmeans")

@dataclass(frozen=True)
class AssignConfig:
    """Settings of the word-assignment objective (the encoder's own settings stay in AeConfig:
    arch, latent_dim, learning_rate, max_epochs, patience, min_delta, max_seconds, threads).

    temperature_start / temperature_end: tau (unitless, in codebook spacings) at epoch 1 and from
        epoch anneal_epochs + 1 on; geometric in between.
    balance_weight: weight of the word-usage term. recon_weight: weight of the BCE
        reconstruction term (0: encoder trained by the assignment alone, decoder unused).
    track_batch: tracks per step; descriptor_batch: independent training descriptors per step
        (they enter the balance term and the reconstruction term).
    refresh_every: every so many steps (and after each epoch) the words take one Lloyd iteration
        on the current codes of the restart sample, so they keep up with the encoder.
    decorrelation_weight: weight of decorrelation_loss on the codes of the independent descriptors.
    usage_momentum: per-step decay of the running word usage of the balance term.
    codebook_update: "ema": the words follow the codes as online k-means (each word the decayed
        mean of the codes nearest to it, per-step decay codebook_decay; no gradient); "gradient":
        the words are trained by the loss like the encoder's weights.
    restart_sample: training descriptors on which dead words are found after each epoch (and,
        init "random", whose initial codes k-means clusters, init_kmeans_iterations iterations,
        into the first words).
    init: "random": a randomly initialised encoder with per-dimension standardised codes, words
        from k-means of its codes; "kmeans": the encoder starts as the projection onto the
        training descriptors' top latent_dim principal axes (exactly linear through its ReLU
        layer, init_linear_pca) with one shared scale for all code dimensions, and the words as
        k-means of all training codes: training starts from a k-means vocabulary and only moves
        away from it where held-out views agree more.
    """

    init: str = "random"
    temperature_start: float = 1.0
    temperature_end: float = 0.3
    anneal_epochs: int = 4
    balance_weight: float = 1.0
    recon_weight: float = 0.0
    track_batch: int = 256
    descriptor_batch: int = 1024
    restart_sample: int = 50_000
    init_kmeans_iterations: int = 10
    usage_momentum: float = 0.99
    codebook_update: str = "ema"
    codebook_decay: float = 0.99
    refresh_every: int = 50
    decorrelation_weight: float = 1.0

    def __post_init__(self) -> None:
        if not (self.temperature_start > 0 and self.temperature_end > 0):
            raise ConfigError("temperatures must be > 0")
        if self.init not in ASSIGN_INITS:
            raise ConfigError(f"init must be one of {ASSIGN_INITS}, got {self.init!r}")
        if self.codebook_update not in ("ema", "gradient") or not 0.0 <= self.codebook_decay < 1.0:
            raise ConfigError("codebook_update must be 'ema' or 'gradient' and codebook_decay in [0, 1)")
        if not 0.0 <= self.usage_momentum < 1.0:
            raise ConfigError(f"usage_momentum must be in [0, 1), got {self.usage_momentum!r}")
        if self.balance_weight < 0 or self.recon_weight < 0:
            raise ConfigError("balance_weight and recon_weight must be >= 0")
        for name in ("anneal_epochs", "track_batch", "descriptor_batch", "restart_sample", "init_kmeans_iterations",
                     "refresh_every"):
            v = getattr(self, name)
            if not isinstance(v, int) or v < (0 if name == "anneal_epochs" else 1):
                raise ConfigError(f"{name} must be a {'non-negative' if name == 'anneal_epochs' else 'positive'} integer, got {v!r}")

    def temperature(self, epoch: int) -> float:
        """tau of a (1-based) epoch."""
        if self.anneal_epochs <= 0 or epoch > self.anneal_epochs:
            return self.temperature_end
        f = (epoch - 1) / self.anneal_epochs
        return self.temperature_start * (self.temperature_end / self.temperature_start) ** f

    def to_dict(self) -> dict:
        return asdict(self)


def squared_distances(z: torch.Tensor, codebook: torch.Tensor) -> torch.Tensor:
    """|z_i - c_k|^2 (N, K) of codes z (N, L) and codebook (K, L), clamped at 0."""
    d2 = (z * z).sum(1, keepdim=True) - 2.0 * z @ codebook.T + (codebook * codebook).sum(1)
    return d2.clamp_min(0.0)


def log_assign(z: torch.Tensor, codebook: torch.Tensor, temperature: float, spacing: float) -> torch.Tensor:
    """log p(k | z) (N, K): log-softmax of -|z - c_k|^2 / (temperature * spacing)."""
    return torch.log_softmax(-squared_distances(z, codebook) / (temperature * spacing), dim=1)


@torch.no_grad()
def codebook_spacing(codebook: torch.Tensor) -> float:
    """Mean over words of the squared distance to the nearest other word (> 0)."""
    d2 = squared_distances(codebook, codebook)
    d2.fill_diagonal_(math.inf)
    return max(float(d2.min(1).values.mean()), 1e-12)


def consistency_loss(logp: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """-mean over valid view pairs of log sum_k p_v(k) p_w(k); logp (B, V, K), mask (B, V) bool."""
    v = logp.shape[1]
    total = logp.new_zeros(())
    count = logp.new_zeros(())
    for a in range(v):
        for b in range(a + 1, v):
            ok = (mask[:, a] & mask[:, b]).to(logp.dtype)
            total = total - (torch.logsumexp(logp[:, a] + logp[:, b], dim=1) * ok).sum()
            count = count + ok.sum()
    return total / count.clamp_min(1.0)


def balance_loss(mean_p: torch.Tensor) -> torch.Tensor:
    """log K - H(mean_p) >= 0 of a mean assignment (K,): 0 when every word is equally used."""
    k = mean_p.shape[0]
    return math.log(k) + (mean_p * torch.log(mean_p.clamp_min(1e-30))).sum()


def decorrelation_loss(z: torch.Tensor) -> torch.Tensor:
    """Sum of squared off-diagonal correlations of a batch of codes z (N, L), divided by L: 0 for
    uncorrelated dimensions, L - 1 when all dimensions carry one feature (a collapse that a
    per-dimension standardisation cannot see)."""
    c = z - z.mean(0)
    c = c / c.pow(2).mean(0).add(1e-6).sqrt()
    corr = (c.T @ c) / z.shape[0]
    off = corr - torch.diag(torch.diagonal(corr))
    return off.pow(2).sum() / z.shape[1]


def running_balance_loss(mean_p: torch.Tensor, usage: torch.Tensor) -> torch.Tensor:
    """log K + sum_k mean_p[k] log usage[k] of a batch's mean assignment mean_p (K,) against a
    running word usage (K,) (detached, sums to 1): equals balance_loss(usage) when mean_p ==
    usage; its gradient, log usage[k], pushes assignments off the words used most over many
    batches (a batch of B << K descriptors cannot estimate the usage of K words by itself)."""
    return math.log(usage.shape[0]) + (mean_p * torch.log(usage.clamp_min(1e-12))).sum()


def assign_loss(logp_tracks: torch.Tensor, mask: torch.Tensor, logp_desc: torch.Tensor | None,
                balance_weight: float, usage: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(total, consistency, balance) of track assignments logp_tracks (B, V, K) with mask (B, V)
    and independent descriptors' logp_desc (M, K) (or None): the balance term's mean assignment
    is over the valid track views and the descriptors; with `usage` (K,) the running form
    (running_balance_loss), else balance_loss of the batch mean."""
    cons = consistency_loss(logp_tracks, mask)
    p = logp_tracks.exp()[mask]
    if logp_desc is not None:
        p = torch.cat([p, logp_desc.exp()])
    mean_p = p.mean(0)
    bal = balance_loss(mean_p) if usage is None else running_balance_loss(mean_p, usage)
    return cons + balance_weight * bal, cons, bal


class StandardizedEncoder(nn.Module):
    """An encoder (B, D) -> (B, L) followed by a standardisation of its codes: centred per
    dimension, divided by each dimension's standard deviation (per_dimension) or by one shared
    scale, the root mean variance over dimensions (which keeps the codes' geometry: distances are
    only rescaled). Batch statistics in training, fixed ones (`calibrate`, then a running mean) in
    eval mode, an affine map the exported graph carries. The codes can neither drift away from the
    words together nor shrink: a collapse that would make every view share one word."""

    def __init__(self, inner: nn.Module, per_dimension: bool = True, momentum: float = 0.01, eps: float = 1e-5) -> None:
        super().__init__()
        self.inner = inner
        self.descriptor_length = inner.descriptor_length
        self.latent_dim = inner.latent_dim
        self.per_dimension = per_dimension
        self.momentum = momentum
        self.eps = eps
        self.register_buffer("running_mean", torch.zeros(inner.latent_dim))
        self.register_buffer("running_var", torch.ones(inner.latent_dim))

    def scaled(self, x: torch.Tensor) -> torch.Tensor:
        return self.inner.scaled(x)

    def _variance(self, z: torch.Tensor) -> torch.Tensor:
        var = z.var(0, unbiased=False)
        return var if self.per_dimension else var.mean().expand_as(var)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        z = self.inner(x)
        if self.training:
            mean, var = z.mean(0), self._variance(z)
            with torch.no_grad():
                self.running_mean.lerp_(mean.detach(), self.momentum)
                self.running_var.lerp_(var.detach(), self.momentum)
        else:
            mean, var = self.running_mean, self.running_var
        return (z - mean) / torch.sqrt(var + self.eps)

    @torch.no_grad()
    def calibrate(self, sample: torch.Tensor) -> torch.Tensor:
        """Set the eval-mode statistics to those of the inner codes of `sample` (M, D); returns the
        standardised codes (M, L)."""
        z = torch.cat([self.inner(sample[s : s + 8192]) for s in range(0, sample.shape[0], 8192)])
        self.running_mean.copy_(z.mean(0))
        self.running_var.copy_(self._variance(z))
        return (z - self.running_mean) / torch.sqrt(self.running_var + self.eps)


@torch.no_grad()
def init_linear_pca(encoder: nn.Module, sample: torch.Tensor) -> None:
    """Set a light encoder (one hidden ReLU layer of width H >= 2 L) to the exact linear map
    x -> P (s(x) - mean): P (L, D) the top L principal axes of the scaled `sample` (M, D). The
    hidden layer carries +P and -P and the output layer their difference, so the ReLU passes
    the projection through unchanged; the extra hidden units start at zero."""
    body = getattr(encoder, "body", None)
    lat = int(encoder.latent_dim)
    if body is None or len(body) != 3 or body[0].out_features < 2 * lat:
        raise ConfigError(f"init 'kmeans' needs a light encoder with one hidden layer of >= {2 * lat} units")
    x = torch.cat([encoder.scale(sample[s : s + 8192]) for s in range(0, sample.shape[0], 8192)]).double()
    mean = x.mean(0)
    cov = (x - mean).T @ (x - mean) / x.shape[0]
    _, vecs = torch.linalg.eigh(cov)  # ascending eigenvalues
    p = vecs[:, -lat:].flip(1).T  # (L, D), largest variance first
    p = p * torch.where(p.sum(1, keepdim=True) < 0, -1.0, 1.0)  # a fixed sign per axis
    first, last = body[0], body[2]
    first.weight.zero_()
    first.bias.zero_()
    first.weight[:lat] = p.float()
    first.weight[lat : 2 * lat] = -p.float()
    first.bias[:lat] = -(p @ mean).float()
    first.bias[lat : 2 * lat] = (p @ mean).float()
    last.weight.zero_()
    last.bias.zero_()
    last.weight[:, :lat] = torch.eye(lat)
    last.weight[:, lat : 2 * lat] = -torch.eye(lat)


@torch.no_grad()
def start_vocabulary(model: Autoencoder, train: torch.Tensor, restart: torch.Tensor, words: int, acfg: AssignConfig,
                     seed: int) -> torch.Tensor:
    """Wrap model.encoder in its StandardizedEncoder and return the first words (K, L) float32:
    k-means of the initial codes. init "random": codes of a random encoder on `restart`,
    standardised per dimension; "kmeans": the principal-axes projection (init_linear_pca) of all
    of `train`, under one shared scale, i.e. a k-means vocabulary of the descriptors themselves
    up to the axes left out."""
    pca = acfg.init == "kmeans"
    if pca:
        init_linear_pca(model.encoder, train)
    model.encoder = StandardizedEncoder(model.encoder, per_dimension=not pca)
    z0 = model.encoder.calibrate(train if pca else restart).numpy()
    words_0 = fit_kmeans(z0, words, KMeansConfig(max_iterations=acfg.init_kmeans_iterations, seed=seed))
    return torch.from_numpy(np.ascontiguousarray(words_0, np.float32))


@dataclass
class AssignResult:
    """What train_assign returns: model (Autoencoder, eval mode; the encoder is exported),
    codebook (K, latent_dim) float32 (the bundle's words), the resolved AeConfig, the AssignConfig,
    and per epoch history (epoch 0: before training) {"epoch", "temperature", "train_loss", "val_loss", "val_consistency",
    "val_balance", "val_recon", "val_agreement" (share of held-out view pairs with one hard word),
    "val_perplexity" (exp entropy of held-out hard word usage, in words), "restarted" (empty words
    re-seeded by the epoch's refreshes), "seconds"}."""

    model: Autoencoder
    codebook: np.ndarray
    config: AeConfig
    assign: AssignConfig
    best_val_loss: float
    best_epoch: int
    epochs_run: int
    n_train: int
    n_val: int
    n_tracks_train: int
    n_tracks_val: int
    seconds: float
    history: list[dict] = field(default_factory=list)
    stop_reason: str = "max_epochs"

    def summary(self) -> dict:
        """JSON-able training summary for the bundle manifest (same keys as TrainResult.summary, plus
        "objective" and "assign")."""
        train_loss = self.history[self.best_epoch]["train_loss"] if self.history else None
        loss = "assign" + ("+bce" if self.assign.recon_weight > 0 else "")
        return {**training_summary(self, loss, train_loss, self.n_tracks_train, self.n_tracks_val),
                "objective": "assign", "n_tracks_train": self.n_tracks_train, "n_tracks_val": self.n_tracks_val,
                "assign": self.assign.to_dict()}


def train_assign(
    vectors: np.ndarray,
    tracks: Tracks,
    val_tracks: Tracks,
    *,
    words: int,
    feature_kind: str,
    seed: int = 0,
    config: AeConfig | None = None,
    assign: AssignConfig | None = None,
) -> AssignResult:
    """Train encoder and codebook on descriptor vectors (N, D) float32 and multi-view tracks
    (train: `tracks`, early stopping: `val_tracks`, from other images). words: K.
    Same inputs, seed and config.threads -> bit-identical weights and codebook (unless
    config.max_seconds ends the run)."""
    from tqdm import tqdm

    vectors = _check_train_vectors(vectors)
    d = int(vectors.shape[1])
    cfg = (config or AeConfig(arch="light")).resolved(d, feature_kind)
    acfg = assign or AssignConfig()
    for name, t in (("tracks", tracks), ("val_tracks", val_tracks)):
        if t.x.ndim != 3 or t.x.shape[2] != d or t.x.shape[1] < 3 or len(t) < 2:
            raise InputError(f"{name} must hold >= 2 tracks of >= 3 views of length {d}, got shape {t.x.shape}")
    if not isinstance(words, int) or words < 2 or words > min(vectors.shape[0] // 2, acfg.restart_sample):
        raise ConfigError(f"words must be an integer in [2, min(N / 2, restart_sample)], got {words!r}")
    t0 = time.perf_counter()
    train, val = held_out_descriptors(vectors, cfg, seed)
    restart = train[: acfg.restart_sample]  # rows already in random order
    tx = torch.from_numpy(np.ascontiguousarray(tracks.x, np.float32))
    tm = torch.from_numpy(np.ascontiguousarray(tracks.mask, bool))
    vx = torch.from_numpy(np.ascontiguousarray(val_tracks.x, np.float32))
    vm = torch.from_numpy(np.ascontiguousarray(val_tracks.mask, bool))
    use_recon = acfg.recon_weight > 0

    with deterministic_torch(cfg.threads):
        torch.manual_seed(seed)
        model = Autoencoder(d, cfg)
        codebook = nn.Parameter(start_vocabulary(model, train, restart, words, acfg, seed),
                                requires_grad=acfg.codebook_update == "gradient")
        gen = torch.Generator().manual_seed(seed)
        # Online k-means state ("ema"): decayed count and code sum of each word (pseudo-count 1 to start).
        ema_n = torch.ones(words)
        ema_sum = codebook.detach().clone()
        params = list(model.encoder.parameters()) + ([codebook] if acfg.codebook_update == "gradient" else [])
        if use_recon:
            params += list(model.decoder.parameters())
        opt = torch.optim.Adam(params, lr=cfg.learning_rate, weight_decay=cfg.weight_decay)
        bce = nn.BCEWithLogitsLoss()
        model.eval()
        # Epoch 0: the initial encoder and its k-means words, a candidate like any epoch.
        history: list[dict] = [epoch_record(model, codebook.detach(), vx, vm, val, acfg, epoch=0, temperature=None,
                                            train_loss=None, restarted=0, seconds=0.0)]
        best, best_epoch, bad = history[0]["val_loss"], 0, 0
        best_state = (copy.deepcopy(model.state_dict()), codebook.detach().clone())
        usage = torch.full((words,), 1.0 / words)  # running soft word usage (balance term)
        epochs_run, stop = 0, "max_epochs"
        n_steps = math.ceil(tx.shape[0] / acfg.track_batch)
        for epoch in range(1, cfg.max_epochs + 1):
            if cfg.max_seconds is not None and time.perf_counter() - t0 >= cfg.max_seconds:
                stop = "budget"
                break
            te = time.perf_counter()
            tau = acfg.temperature(epoch)
            spacing = codebook_spacing(codebook.detach())
            model.train()
            order = torch.randperm(tx.shape[0], generator=gen)
            d_order = torch.randperm(train.shape[0], generator=gen)
            n_db = max(1, train.shape[0] // acfg.descriptor_batch)
            total, count = 0.0, 0
            bar = tqdm(range(n_steps), desc=f"AE assign epoch {epoch}/{cfg.max_epochs}", unit="batch",
                       disable=not cfg.progress, leave=False, mininterval=0.5)
            refreshed = 0
            for s in bar:
                if s > 0 and s % acfg.refresh_every == 0:
                    refreshed += _refresh_words(model, codebook, restart, ema_n, ema_sum)
                    spacing = codebook_spacing(codebook.detach())
                idx = order[s * acfg.track_batch : (s + 1) * acfg.track_batch]
                if idx.numel() < 2:
                    continue
                x, m = tx[idx], tm[idx]
                b, v = x.shape[0], x.shape[1]
                j = d_order[(s % n_db) * acfg.descriptor_batch : (s % n_db + 1) * acfg.descriptor_batch]
                xd = train[j]
                z = model.encoder(torch.cat([x.reshape(b * v, d), xd]))
                d2 = squared_distances(z, codebook)
                logp = torch.log_softmax(-d2 / (tau * spacing), dim=1)
                with torch.no_grad():
                    batch_p = torch.cat([logp[: b * v].exp()[m.reshape(-1)], logp[b * v :].exp()]).mean(0)
                    usage.mul_(acfg.usage_momentum).add_(batch_p, alpha=1.0 - acfg.usage_momentum)
                loss, _, _ = assign_loss(logp[: b * v].view(b, v, -1), m, logp[b * v :], acfg.balance_weight, usage)
                if acfg.decorrelation_weight > 0:
                    loss = loss + acfg.decorrelation_weight * decorrelation_loss(z[b * v :])
                if use_recon:
                    loss = loss + acfg.recon_weight * bce(model.decoder(z[b * v :]), model.encoder.scaled(xd))
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
                if acfg.codebook_update == "ema":
                    with torch.no_grad():  # online k-means step on this batch's codes (before the step)
                        hard = d2.detach().argmin(1)
                        ema_n.mul_(acfg.codebook_decay).add_(torch.bincount(hard, minlength=words).to(ema_n.dtype),
                                                             alpha=1.0 - acfg.codebook_decay)
                        ema_sum.mul_(acfg.codebook_decay).index_add_(0, hard, z.detach(), alpha=1.0 - acfg.codebook_decay)
                        codebook.copy_(ema_sum / ema_n.clamp_min(1e-6)[:, None])
                total += loss.item() * b
                count += b
                if s % 20 == 0:
                    bar.set_postfix(loss=f"{total / max(count, 1):.4f}")
            bar.close()
            model.eval()
            restarted = refreshed + _refresh_words(model, codebook, restart, ema_n, ema_sum)
            epochs_run = epoch
            history.append(epoch_record(model, codebook.detach(), vx, vm, val, acfg, epoch=epoch,
                                        temperature=round(tau, 6), train_loss=total / max(count, 1),
                                        restarted=restarted, seconds=round(time.perf_counter() - te, 2)))
            val_loss = history[-1]["val_loss"]
            if val_loss < best - cfg.min_delta:
                best, best_epoch, bad = val_loss, epoch, 0
                best_state = (copy.deepcopy(model.state_dict()), codebook.detach().clone())
            elif epoch > acfg.anneal_epochs:
                bad += 1
                if bad > cfg.patience:
                    stop = "patience"
                    break
        model.load_state_dict(best_state[0])
        model.eval()
    return AssignResult(model, best_state[1].numpy().astype(np.float32), cfg, acfg, best, best_epoch, epochs_run,
                        int(train.shape[0]), int(val.shape[0]), len(tracks), len(val_tracks),
                        time.perf_counter() - t0, history, stop)


def epoch_record(model: Autoencoder, codebook: torch.Tensor, vx: torch.Tensor, vm: torch.Tensor, val: torch.Tensor,
                 acfg: AssignConfig, **fields) -> dict:
    """One history entry: `fields` (epoch, temperature, train_loss, restarted, seconds) and the
    held-out figures of the model as it stands, the same at every epoch, the initial one
    included: evaluate_assign on the held-out tracks vx (T, V, D) / vm (T, V) at the final
    temperature, plus, with a reconstruction term, recon_weight times the BCE reconstruction
    of the held-out descriptors val (N, D), in "val_loss"."""
    ev = evaluate_assign(model, codebook, vx, vm, acfg.temperature_end, codebook_spacing(codebook), acfg.balance_weight)
    recon = evaluate_loss(model, val, 2048) if acfg.recon_weight > 0 else None
    return {**fields, "val_loss": ev["loss"] + (acfg.recon_weight * recon if recon is not None else 0.0),
            "val_consistency": ev["consistency"], "val_balance": ev["balance"], "val_recon": recon,
            "val_match": None, "val_agreement": ev["agreement"], "val_perplexity": ev["perplexity"]}


@torch.no_grad()
def _refresh_words(model: Autoencoder, codebook: nn.Parameter, sample: torch.Tensor, ema_n: torch.Tensor,
                   ema_sum: torch.Tensor) -> int:
    """One Lloyd iteration of the words on the current codes of `sample` (M, D) (eval-mode
    statistics recalibrated on it first; empty words re-seeded on the farthest codes, as
    trainer/aefabmap_trainer/kmeans.py does); the online state keeps its counts. Returns the number of empty words."""
    from aefabmap_trainer.kmeans import _assign, _update

    was_training = model.training
    model.eval()
    z = model.encoder.calibrate(sample).numpy()
    old = codebook.detach().numpy().copy()
    labels, dist = _assign(z, old)
    empty = int(np.sum(np.bincount(labels, minlength=old.shape[0]) == 0))
    new = torch.from_numpy(_update(z, labels, dist, old))
    codebook.copy_(new)
    ema_sum.copy_(new * ema_n[:, None])
    model.train(was_training)
    return empty


@torch.no_grad()
def evaluate_assign(model: Autoencoder, codebook: torch.Tensor, x: torch.Tensor, mask: torch.Tensor,
                    temperature: float, spacing: float, balance_weight: float, chunk: int = 512) -> dict:
    """Held-out figures of tracks x (T, V, D) with mask (T, V): soft loss at `temperature`
    (consistency, balance over all valid views, total), hard pair agreement and the perplexity of
    hard word usage (words)."""
    k = codebook.shape[0]
    cons_sum, cons_n, agree, pairs_n = 0.0, 0.0, 0.0, 0.0
    mean_p = torch.zeros(k, dtype=torch.float64)
    usage = torch.zeros(k, dtype=torch.float64)
    n_views = 0
    t, v, d = x.shape
    for s in range(0, t, chunk):
        xs, ms = x[s : s + chunk], mask[s : s + chunk]
        b = xs.shape[0]
        z = model.encoder(xs.reshape(b * v, d))
        logp = log_assign(z, codebook, temperature, spacing).view(b, v, k)
        hard = squared_distances(z, codebook).argmin(1).view(b, v)
        for a in range(v):
            for c in range(a + 1, v):
                ok = ms[:, a] & ms[:, c]
                n = float(ok.sum())
                cons_sum += -float((torch.logsumexp(logp[:, a] + logp[:, c], dim=1) * ok).sum())
                agree += float(((hard[:, a] == hard[:, c]) & ok).sum())
                cons_n += n
                pairs_n += n
        mean_p += logp.exp()[ms].sum(0).double()
        usage += torch.bincount(hard[ms], minlength=k).double()
        n_views += int(ms.sum())
    mean_p /= max(n_views, 1)
    u = usage / max(n_views, 1)
    consistency = cons_sum / max(cons_n, 1.0)
    balance = float(balance_loss(mean_p))
    perplexity = float(torch.exp(-(u[u > 0] * torch.log(u[u > 0])).sum()))
    return {"loss": consistency + balance_weight * balance, "consistency": consistency, "balance": balance,
            "agreement": agree / max(pairs_n, 1.0), "perplexity": perplexity}
