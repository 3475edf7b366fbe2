"""Train the learned ORB descriptor (runtime/aefabmap_runtime/core/features/learned_description.py).

Pairs: each training image (outside the test split, multiview.is_test_image) against a copy seen
through a random homography (match_pairs.random_homography, its range one of WARPS) once at a
random synthetic night (multiview.night) and once under a random photometric change
(multiview.photometric). Keypoints are ORB's, detected on both as the runtime detects them for
verification (its keypoint budget, VerificationConfig.keypoints, when above the vocabulary's); a
pair is two keypoints that land within MATCH_RADIUS detection pixels of each other through the
homography, each the other's nearest, on pyramid levels at most one apart. Both patches are read as the runtime reads them, orientation
and level as detected, so the pairs carry the detector's own errors.

Objective: for a batch of pairs, the bits relaxed to tanh of the projection of the normalised
patch; each pair's distance (the share of differing bits) must undercut the closest other patch of
the batch on either side by MARGIN (in-batch hardest negative), with terms pushing the relaxed bits
to +-1 and each bit to be set half the time. The weights are then scaled per row to int8 (a bit's
sign does not depend on its row's scale).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from aefabmap_runtime.adapters.frames import load_image
from aefabmap_runtime.core.features.features import FeatureConfig, FeatureExtractor, to_gray
from aefabmap_runtime.core.features.learned_description import BITS, SAMPLES, LearnedDescription
from aefabmap_runtime.core.verify.verification import VerificationConfig
from aefabmap_runtime.errors import ConfigError
from aefabmap_trainer.match_pairs import random_homography
from aefabmap_trainer.multiview import is_test_image, night, photometric

#: Largest distance (detection pixels) between a keypoint mapped through the homography and its
#: partner, and the largest difference of their pyramid levels.
MATCH_RADIUS = 2.5
MAX_LEVEL_GAP = 1
#: The objective's margin (share of bits), its regularisers' weights and the learning rate.
MARGIN = 0.25
QUANT_WEIGHT = 0.05
BALANCE_WEIGHT = 0.1
LEARNING_RATE = 2e-3
#: The patch's contrast floor in training (grey levels): a flat patch's noise is not blown up.
CONTRAST_FLOOR = 4.0
#: The homographies' ranges (`random_homography`'s keywords). "residual": what the detector's own
#: normalisation leaves of a viewpoint change: half a pyramid step of scale either way (ORB's levels
#: are 1.2 apart), a few degrees of orientation error and a little perspective, so the bits learn
#: the light across those small changes and keep ORB's selectivity for the rest of the geometry,
#: which the pyramid, the orientation and the upright retry handle. "wide": rotations of 20
#: degrees, scales of 0.75-1.25 and 15 % corner jitter, invariance that also makes look-alike
#: structures agree (docs/results.md, "A learned descriptor").
WARPS = {
    "residual": {"max_angle_deg": 5.0, "scale_range": (0.9, 1.1), "max_perspective": 0.03},
    "wide": {"max_angle_deg": 20.0, "scale_range": (0.75, 1.25), "max_perspective": 0.15},
}


@dataclass(frozen=True)
class DescriptorTraining:
    """images: training images drawn (each gives a night and a photometric pair);
    epochs: passes over the pairs; batch: pairs per step (each pair's negatives are the batch's
    other patches); seed: of the images drawn, the warps and the training; threads: torch's threads;
    warp: the homographies' range, a key of WARPS."""

    images: int = 2400
    epochs: int = 6
    batch: int = 1024
    seed: int = 0
    threads: int = 1
    warp: str = "residual"

    def __post_init__(self) -> None:
        if not (isinstance(self.images, int) and self.images >= 1):
            raise ConfigError(f"--descriptor-images must be an integer >= 1, got {self.images!r}")
        if not (isinstance(self.epochs, int) and 1 <= self.epochs <= 100):
            raise ConfigError(f"--descriptor-epochs must be an integer in [1, 100], got {self.epochs!r}")
        if not (isinstance(self.batch, int) and self.batch >= 16):
            raise ConfigError(f"the learned descriptor's batch must be an integer >= 16, got {self.batch!r}")
        if self.warp not in WARPS:
            raise ConfigError(f"--descriptor-warp must be one of {sorted(WARPS)}, got {self.warp!r}")


def corresponding_patches(files: list[Path], features: FeatureConfig, config: DescriptorTraining,
                          show_progress: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """(a, b): (P, SAMPLES) uint8 patches of corresponding keypoints (module docstring)."""
    budget = max(features.max_features, VerificationConfig().keypoints or 0)
    extractor = FeatureExtractor(replace(features, descriptor="brief", max_features=budget))
    pool = [f for f in files if not is_test_image(f)]
    if not pool:
        raise ConfigError("no training image outside the test split for the learned descriptor")
    rng = np.random.default_rng(config.seed)
    chosen = rng.choice(len(pool), size=min(config.images, len(pool)), replace=False)
    a_rows, b_rows = [], []
    for i in tqdm(sorted(chosen.tolist()), desc="descriptor pairs", disable=not show_progress, mininterval=1.0):
        gray = to_gray(load_image(pool[i]))
        ka, la, pa = extractor.keypoint_patches(gray)
        if len(ka) == 0:
            continue
        for relight in (night, photometric):
            h = random_homography(gray.shape[:2], rng, **WARPS[config.warp])
            seen = relight(cv2.warpPerspective(gray, h, (gray.shape[1], gray.shape[0]), flags=cv2.INTER_LINEAR), rng)
            kb, lb, pb = extractor.keypoint_patches(seen)
            if len(kb) == 0:
                continue
            ia, ib = _pairs(ka, la, kb, lb, h, _detection_scale(features, gray.shape))
            a_rows.append(pa[ia])
            b_rows.append(pb[ib])
    if not a_rows:
        return np.zeros((0, SAMPLES), np.uint8), np.zeros((0, SAMPLES), np.uint8)
    return np.concatenate(a_rows), np.concatenate(b_rows)


def _detection_scale(features: FeatureConfig, shape_hw: tuple[int, int]) -> float:
    """Detection pixels per image pixel (FeatureConfig.long_side)."""
    return 1.0 if features.long_side is None else features.long_side / max(shape_hw)


def _pairs(ka: np.ndarray, la: np.ndarray, kb: np.ndarray, lb: np.ndarray, h: np.ndarray,
           scale: float) -> tuple[np.ndarray, np.ndarray]:
    """Indices (ia, ib) of mutual nearest keypoints within MATCH_RADIUS detection pixels through
    the homography h (image pixels), on levels at most MAX_LEVEL_GAP apart."""
    mapped = cv2.perspectiveTransform(ka.reshape(-1, 1, 2).astype(np.float64), h).reshape(-1, 2)
    dist = np.linalg.norm(mapped[:, None, :] - kb[None, :, :].astype(np.float64), axis=2) * scale
    nearest = dist.argmin(axis=1)
    rows = np.arange(len(ka))
    ok = (dist[rows, nearest] < MATCH_RADIUS) & (np.abs(la - lb[nearest]) <= MAX_LEVEL_GAP)
    ok &= dist.argmin(axis=0)[nearest] == rows
    return rows[ok], nearest[ok]


def normalised(patches: np.ndarray) -> np.ndarray:
    """(N, SAMPLES) float32: each patch minus its mean, over its standard deviation plus CONTRAST_FLOOR."""
    x = patches.astype(np.float32)
    x -= x.mean(axis=1, keepdims=True)
    x /= x.std(axis=1, keepdims=True) + CONTRAST_FLOOR
    return x


def train_projection(a: np.ndarray, b: np.ndarray, config: DescriptorTraining,
                     show_progress: bool = True) -> LearnedDescription:
    """The projection learned from corresponding patches a, b (P, SAMPLES) uint8 (module docstring)."""
    import torch

    batch = config.batch
    if len(a) < 2 * batch:
        raise ConfigError(f"the learned descriptor needs at least {2 * batch} corresponding keypoints, found {len(a)}")
    torch.manual_seed(config.seed)
    torch.set_num_threads(config.threads)
    xa, xb = torch.from_numpy(normalised(a)), torch.from_numpy(normalised(b))
    layer = torch.nn.Linear(SAMPLES, BITS, bias=False)
    optimiser = torch.optim.Adam(layer.parameters(), lr=LEARNING_RATE)
    steps_per_epoch = len(a) // batch
    schedule = torch.optim.lr_scheduler.OneCycleLR(optimiser, max_lr=LEARNING_RATE,
                                                   total_steps=config.epochs * steps_per_epoch)
    generator = torch.Generator().manual_seed(config.seed)
    others = ~torch.eye(batch, dtype=torch.bool)
    bar = tqdm(total=config.epochs * steps_per_epoch, desc="descriptor", disable=not show_progress, mininterval=1.0)
    for _ in range(config.epochs):
        order = torch.randperm(len(a), generator=generator)
        for step in range(steps_per_epoch):
            rows = order[step * batch:(step + 1) * batch]
            ta, tb = torch.tanh(layer(xa[rows])), torch.tanh(layer(xb[rows]))
            share = torch.cdist(ta, tb) ** 2 / (4 * BITS)  # ~ the share of differing bits
            closest = share.masked_fill(~others, math.inf)
            negative = torch.minimum(closest.min(dim=1).values, closest.min(dim=0).values)
            loss = torch.relu(MARGIN + share.diagonal() - negative).mean()
            loss = loss + QUANT_WEIGHT * ((1 - ta.abs()).mean() + (1 - tb.abs()).mean())
            loss = loss + BALANCE_WEIGHT * (ta.mean(dim=0) ** 2).mean()
            optimiser.zero_grad()
            loss.backward()
            optimiser.step()
            schedule.step()
            bar.update(1)
    bar.close()
    return LearnedDescription(to_int8(layer.weight.detach().numpy()))


def to_int8(weights: np.ndarray) -> np.ndarray:
    """(BITS, SAMPLES) float weights scaled per row so that the largest is +-127, rounded to int8."""
    peak = np.abs(weights).max(axis=1, keepdims=True)
    peak[peak == 0] = 1.0
    return np.clip(np.rint(weights / peak * 127.0), -127, 127).astype(np.int8)


def train_learned_description(files: list[Path], features: FeatureConfig, config: DescriptorTraining,
                              show_progress: bool = True) -> tuple[LearnedDescription, int]:
    """The learned descriptor of these training images, and how many keypoint pairs trained it."""
    a, b = corresponding_patches(files, features, config, show_progress)
    return train_projection(a, b, config, show_progress), len(a)
