#!/usr/bin/env python
"""Would a small learned detector find more of the day's corners at night than ORB's?

A probe of issue 55's "learned keypoints", one pyramid level: frames at the 512-px detection
scale, contrast-stretched as the runtime stretches them. The teacher is ORB's own detector on that
level (FAST, then the Harris ranking: `cv2.ORB`, one level). The net is three 3 x 3 convolutions
(strides 2, 2 and 1, ReLU) and a 1 x 1 head whose 16 channels are the pixels of a 4 x 4 cell
(pixel shuffle): a score per pixel. It is trained with torch on the training images outside the
test split (`trainer.multiview.is_test_image`), with a binary cross-entropy against the teacher's
corners of the day image, the input being that image with day noise or under a random synthetic
night (gain, gamma, blur and noise drawn around `trainer.multiview.NIGHT`). With `--stable K` the
label keeps only the day corners that ORB finds again (within REPEAT_RADIUS) in at least K of
four random nights of the image: the net is asked for the corners the night leaves.

Measured on the test split, for ORB's detector and the net alike: of the day frame's KEYPOINTS
strongest corners (the net's: peaks of its scores, 5 x 5 non-maximum suppression), the share
repeated, a corner of the same frame under the condition lying within REPEAT_RADIUS pixels. And
the net's cost on one level of the 512-px frame: CPU ms of one onnxruntime run on one thread,
float32 and int8 (static QDQ quantisation).

    python scripts/night_detector_probe.py --data DATA [--widths 16,32,64] [--stable 2] --json probe.json
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import onnxruntime as ort
import torch
import torch.nn.functional as F
from onnxruntime.quantization import (
    CalibrationDataReader,
    QuantFormat,
    QuantType,
    quantize_static,
)
from scipy.spatial import cKDTree
from torch import nn
from tqdm import tqdm

from aefabmap_runtime.core.features.features import detection_scale, stretch_contrast
from aefabmap_runtime.errors import AefabmapError
from aefabmap_trainer.multiview import NIGHT, darken, is_test_image

#: The detection scale (px of the long side) and ORB's border (px) where no corner is kept.
LONG_SIDE = 512
BORDER = 16
#: Corners compared per frame, and per training label (the verification budget's order).
KEYPOINTS = 500
LABEL_KEYPOINTS = 1000
#: A corner repeats within this many pixels.
REPEAT_RADIUS = 2.0
#: Random nights a label's corner is looked for in (`--stable`).
LABEL_NIGHTS = 4
#: Training crops (px), batch size, learning rate and its drop for the last 30 % of steps.
CROP = 160
BATCH = 16
LEARNING_RATE = 2e-3
LATE_RATE = 5e-4
#: A label pixel weighs this much more than a background pixel (corners are sparse).
POSITIVE_WEIGHT = 20.0
DAY_NOISE = {"gain": 1.0, "gamma": 1.0, "noise": 2.0, "blur": 0.0}
CONDITIONS = {
    "day noise": DAY_NOISE,
    "gamma": {"gain": 1.0, "gamma": NIGHT["gamma"], "noise": 0.0, "blur": 0.0},
    "night": dict(NIGHT),
}


def load_level(path: Path) -> np.ndarray:
    """A training image as grey levels (H, W) uint8, resized as the runtime resizes a frame to a
    LONG_SIDE detection scale."""
    gray = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if gray is None:
        raise AefabmapError(f"cannot read image {path}")
    return detection_scale(gray, LONG_SIDE)[0]


def orb_corners(level: np.ndarray, count: int = KEYPOINTS) -> np.ndarray:
    """(N, 2) float32 x, y of ORB's strongest `count` corners on one level (FAST, Harris ranking)."""
    orb = cv2.ORB_create(nfeatures=count, nlevels=1, edgeThreshold=BORDER, fastThreshold=20)
    return np.array([k.pt for k in orb.detect(level, None)], np.float32).reshape(-1, 2)


def random_night(gray: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """gray under a synthetic night drawn around NIGHT (from a mild dusk to beyond it)."""
    return darken(gray, rng, gain=rng.uniform(0.2, 1.0), gamma=rng.uniform(1.0, 2.6), noise=rng.uniform(1.0, 5.0),
                  blur=rng.uniform(0.0, 1.0))


def repeated(day: np.ndarray, other: np.ndarray) -> np.ndarray:
    """(N,) bool: each day corner (N, 2) has a corner of `other` (M, 2) within REPEAT_RADIUS."""
    if len(day) == 0 or len(other) == 0:
        return np.zeros(len(day), bool)
    dist, _ = cKDTree(other).query(day)
    return dist <= REPEAT_RADIUS


def label_map(gray: np.ndarray, stable: int, rng: np.random.Generator) -> np.ndarray:
    """(H, W) float32 1 at the teacher's day corners of gray (raw grey levels), 0 elsewhere; with
    `stable` > 0 only the corners found again in at least that many of LABEL_NIGHTS nights."""
    corners = orb_corners(stretch_contrast(gray), LABEL_KEYPOINTS)
    if stable > 0:
        hits = sum(repeated(corners, orb_corners(stretch_contrast(random_night(gray, rng)), LABEL_KEYPOINTS)).astype(int)
                   for _ in range(LABEL_NIGHTS))
        corners = corners[hits >= stable]
    label = np.zeros(gray.shape, np.float32)
    xy = np.rint(corners).astype(int)
    label[np.clip(xy[:, 1], 0, gray.shape[0] - 1), np.clip(xy[:, 0], 0, gray.shape[1] - 1)] = 1.0
    return label


class CornerNet(nn.Module):
    """Scores (B, 1, H, W) of a stretched frame (B, 1, H, W), H and W multiples of 4."""

    def __init__(self, widths: tuple[int, int, int]) -> None:
        super().__init__()
        self.convs = nn.ModuleList([nn.Conv2d(1, widths[0], 3, 2, 1), nn.Conv2d(widths[0], widths[1], 3, 2, 1),
                                    nn.Conv2d(widths[1], widths[2], 3, 1, 1)])
        self.head = nn.Conv2d(widths[2], 16, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        for conv in self.convs:
            x = F.relu(conv(x))
        return F.pixel_shuffle(self.head(x), 4)


def as_input(level: np.ndarray) -> torch.Tensor:
    """(1, 1, H, W) float32 of a stretched uint8 level, centred and scaled."""
    return (torch.from_numpy(np.ascontiguousarray(level)).float()[None, None] / 255.0 - 0.5) / 0.25


def net_corners(net: CornerNet, level: np.ndarray, count: int = KEYPOINTS) -> np.ndarray:
    """(N, 2) float32 x, y of the net's `count` strongest score peaks on a stretched level."""
    h, w = level.shape
    padded = np.pad(level, ((0, -h % 4), (0, -w % 4)), mode="edge")
    with torch.no_grad():
        score = net(as_input(padded))[0, 0, :h, :w]
    peak = score == F.max_pool2d(score[None, None], 5, 1, 2)[0, 0]
    peak[:BORDER], peak[-BORDER:], peak[:, :BORDER], peak[:, -BORDER:] = False, False, False, False
    ys, xs = torch.nonzero(peak, as_tuple=True)
    order = torch.argsort(score[ys, xs], descending=True)[:count]
    return np.stack([xs[order].numpy(), ys[order].numpy()], 1).astype(np.float32)


def train(images: list[Path], widths: tuple[int, int, int], stable: int, steps: int, seed: int,
          show_progress: bool) -> CornerNet:
    """CornerNet trained on `images` (module docstring), seeded by `seed`."""
    rng = np.random.default_rng(seed)
    torch.manual_seed(seed)
    grays, labels = [], []
    for path in tqdm(images, desc="labels", disable=not show_progress, mininterval=1.0):
        grays.append(load_level(path))
        labels.append(label_map(grays[-1], stable, rng))
    crop = min(CROP, *(min(g.shape) for g in grays)) // 4 * 4
    net = CornerNet(widths)
    optimiser = torch.optim.Adam(net.parameters(), LEARNING_RATE)
    for step in tqdm(range(steps), desc="steps", disable=not show_progress, mininterval=1.0):
        if step == int(0.7 * steps):
            for group in optimiser.param_groups:
                group["lr"] = LATE_RATE
        inputs, targets = [], []
        for _ in range(BATCH):
            k = int(rng.integers(len(grays)))
            gray = grays[k]
            y0, x0 = int(rng.integers(0, gray.shape[0] - crop + 1)), int(rng.integers(0, gray.shape[1] - crop + 1))
            seen = darken(gray, rng, **DAY_NOISE) if rng.random() < 0.5 else random_night(gray, rng)
            inputs.append(as_input(stretch_contrast(seen)[y0:y0 + crop, x0:x0 + crop])[0])
            targets.append(torch.from_numpy(labels[k][y0:y0 + crop, x0:x0 + crop])[None])
        x, y = torch.stack(inputs), torch.stack(targets)
        soft = 0.5 * (y + F.max_pool2d(y, 3, 1, 1))  # a pixel beside a corner is half a corner
        loss = F.binary_cross_entropy_with_logits(net(x), soft, pos_weight=torch.tensor(POSITIVE_WEIGHT))
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
    return net.eval()


def repeatability(net: CornerNet, images: list[Path], seed: int, show_progress: bool) -> dict:
    """{condition: {"orb": share, "learned": share}}: the day corners repeated under each condition,
    averaged over `images`; each image's noise from a generator seeded by `seed` and its index."""
    shares = {name: {"orb": [], "learned": []} for name in CONDITIONS}
    for i, path in enumerate(tqdm(images, desc="test images", disable=not show_progress, mininterval=1.0)):
        gray = load_level(path)
        day = stretch_contrast(gray)
        orb_day, net_day = orb_corners(day), net_corners(net, day)
        for name, condition in CONDITIONS.items():
            seen = stretch_contrast(darken(gray, np.random.default_rng([seed, i]), **condition))
            shares[name]["orb"].append(repeated(orb_day, orb_corners(seen)).mean() if len(orb_day) else 0.0)
            shares[name]["learned"].append(repeated(net_day, net_corners(net, seen)).mean() if len(net_day) else 0.0)
    return {name: {k: float(np.mean(v)) for k, v in row.items()} for name, row in shares.items()}


def cost_ms(net: CornerNet, shape_hw: tuple[int, int], runs: int = 30) -> dict:
    """{"float32": ms, "int8": ms}: median CPU time of one onnxruntime run (one thread) of the net
    on a (1, 1, H, W) input, exported as float32 and quantised statically to int8."""
    inputs = np.random.default_rng(0).normal(0.0, 1.0, (8, 1, 1, *shape_hw)).astype(np.float32)

    class Calibration(CalibrationDataReader):
        def __init__(self) -> None:
            self.batches = iter({"x": x} for x in inputs)

        def get_next(self):
            return next(self.batches, None)

    with tempfile.TemporaryDirectory() as tmp:
        fp32, int8 = Path(tmp) / "net.onnx", Path(tmp) / "net_int8.onnx"
        logging.disable(logging.WARNING)  # the exporter's and the quantiser's advice, not the probe's
        try:
            program = torch.onnx.export(net, (torch.from_numpy(inputs[0]),), None, input_names=["x"],
                                        output_names=["score"], opset_version=18, dynamo=True, external_data=False,
                                        optimize=True, verbose=False)
            program.save(str(fp32))
            quantize_static(str(fp32), str(int8), Calibration(), quant_format=QuantFormat.QDQ,
                            activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8)
        finally:
            logging.disable(logging.NOTSET)
        return {name: _median_run_ms(path, inputs[0], runs) for name, path in (("float32", fp32), ("int8", int8))}


def _median_run_ms(model: Path, x: np.ndarray, runs: int) -> float:
    """Median CPU ms of one onnxruntime run of `model` on x, one thread, after five that allocate."""
    options = ort.SessionOptions()
    options.intra_op_num_threads = options.inter_op_num_threads = 1
    session = ort.InferenceSession(str(model), options, providers=["CPUExecutionProvider"])
    times = []
    for k in range(runs + 5):
        start = time.process_time()
        session.run(None, {"x": x})
        if k >= 5:
            times.append(time.process_time() - start)
    return 1000.0 * float(np.median(times))


def split(data: Path) -> tuple[list[Path], list[Path]]:
    """(training, test-split) images of DATA/train, by name."""
    images = sorted((data / "train").rglob("*.jpg"))
    return [p for p in images if not is_test_image(p)], [p for p in images if is_test_image(p)]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, required=True, help="the data root (its train/)")
    ap.add_argument("--widths", default="8,16,32", help="channels of the three convolutions (default 8,16,32)")
    ap.add_argument("--stable", type=int, default=2, choices=range(LABEL_NIGHTS + 1),
                    help="label only corners found again in this many of four nights; 0: all (default 2)")
    ap.add_argument("--steps", type=int, default=3000, help="training steps of 16 crops (default 3000)")
    ap.add_argument("--train-images", type=int, default=1500, help="training images used (default 1500)")
    ap.add_argument("--test-images", type=int, default=80, help="test-split images measured (default 80)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=2, help="torch threads for training (default 2)")
    ap.add_argument("--json", type=Path, help="write the parameters, shares and costs here")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    try:
        widths = tuple(int(w) for w in args.widths.split(","))
        if len(widths) != 3 or min(widths) < 1:
            raise AefabmapError(f"--widths wants three positive integers, not {args.widths!r}")
        training, test = split(args.data)
        if not training or not test:
            raise AefabmapError(f"no training or no test-split image under {args.data / 'train'}")
        torch.set_num_threads(args.threads)
        order = np.random.default_rng(args.seed).permutation(len(training))[: args.train_images]
        net = train([training[k] for k in sorted(order)], widths, args.stable, args.steps, args.seed,
                    not args.no_progress)
        test = test[: args.test_images]
        shares = repeatability(net, test, args.seed, not args.no_progress)
        shape = load_level(test[0]).shape
        cost = cost_ms(net, (shape[0] // 4 * 4, shape[1] // 4 * 4))
    except (AefabmapError, OSError, ValueError) as exc:
        print(f"night_detector_probe: {exc}", file=sys.stderr)
        return 1
    print(f"widths {widths}, stable {args.stable}, {args.steps} steps; {len(test)} test images; "
          f"share of the day's {KEYPOINTS} corners repeated")
    for name, row in shares.items():
        print(f"  {name:<10} ORB {row['orb']:.3f}   learned {row['learned']:.3f}")
    print(f"the net on one {shape[1]} x {shape[0]} level, one thread: {cost['float32']:.2f} ms float32, "
          f"{cost['int8']:.2f} ms int8")
    if args.json:
        args.json.write_text(json.dumps({"widths": widths, "stable": args.stable, "steps": args.steps,
                                         "train_images": len(order), "test_images": len(test), "seed": args.seed,
                                         "keypoints": KEYPOINTS, "repeat_radius": REPEAT_RADIUS,
                                         "conditions": CONDITIONS, "repeated": shares,
                                         "cost_ms_one_level": cost, "level_hw": list(shape)}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
