#!/usr/bin/env python
"""A synthetic-night revisit sequence from TRAINING images only, for retrieval and verification under light change.

The sequence holds N training images (CamVid frames of every drive, spaced so that no two show
the same place, and Scene-15 images), then the same N images darkened as at night (exposure cut,
gamma, sensor noise, blur), in a shuffled order so that no track of consecutive revisits helps.
ground truth: the darkened copy of image i revisits frame i. `aefabmap eval` on it then prints
the revisit split: "true place among the checked candidates" is retrieval under the light change,
"verified" is verification (run it with --sequence-frames 0: the shuffled queries form no chains).

    python scripts/light_benchmark.py --data DATA --out night_seq --per-drive 5 --scenes 120
    aefabmap eval --model BUNDLE --images night_seq/images --gt night_seq/gt.npy --exclude 1 \\
        --fabmap-score llr --sequence-frames 0 --json night.json
"""

from __future__ import annotations

import argparse
import os
import random
from pathlib import Path

import cv2
import numpy as np

#: Synthetic night: exposure scale, gamma (> 1 darkens the mid-tones), noise sigma (grey levels), blur sigma (px).
EXPOSURE, GAMMA, NOISE, BLUR = 0.35, 1.6, 4.0, 0.8


def night(gray: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A darkened, noisier, slightly blurred copy of a grey uint8 image."""
    x = (gray.astype(np.float32) / 255.0) ** GAMMA * EXPOSURE * 255.0
    x = cv2.GaussianBlur(x, (0, 0), BLUR)
    x += rng.normal(0.0, NOISE, x.shape).astype(np.float32)
    return np.clip(np.rint(x), 0, 255).astype(np.uint8)


def pick_images(train: Path, per_drive: int, scenes: int, seed: int) -> list[Path]:
    """per_drive CamVid frames per drive, evenly spaced over the drive, and `scenes` Scene-15 images."""
    rng = random.Random(seed)
    camvid = sorted(p for p in (train / "camvid").iterdir() if p.suffix.lower() in (".png", ".jpg"))
    drives: dict[str, list[Path]] = {}
    for p in camvid:
        drives.setdefault(p.name.split("_")[0], []).append(p)
    out = []
    for frames in drives.values():
        step = max(1, len(frames) // per_drive)
        out += frames[::step][:per_drive]
    scene_files = sorted(p for p in (train / "scene15").rglob("*") if p.suffix.lower() in (".png", ".jpg"))
    return out + rng.sample(scene_files, min(scenes, len(scene_files)))


def main(argv: list[str] | None = None) -> None:
    repo = Path(__file__).resolve().parents[1]
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=Path(os.environ.get("AEFABMAP_DATA", repo.parent / "shared" / "data")))
    ap.add_argument("--out", type=Path, required=True, help="folder for images/ and gt.npy")
    ap.add_argument("--per-drive", type=int, default=5,
                    help="CamVid frames per drive (few: frames of one drive close together show one place)")
    ap.add_argument("--scenes", type=int, default=120, help="Scene-15 images")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    sources = pick_images(args.data / "train", args.per_drive, args.scenes, args.seed)
    n = len(sources)
    order = list(range(n))
    random.Random(args.seed + 1).shuffle(order)
    rng = np.random.default_rng(args.seed)
    images = args.out / "images"
    images.mkdir(parents=True, exist_ok=True)
    grays = [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in sources]
    for i, g in enumerate(grays):
        cv2.imwrite(str(images / f"{i:06d}.png"), g)
    gt = np.zeros((2 * n, 2 * n), bool)
    for j, i in enumerate(order):
        cv2.imwrite(str(images / f"{n + j:06d}.png"), night(grays[i], rng))
        gt[n + j, i] = gt[i, n + j] = True
    np.save(args.out / "gt.npy", gt)
    print(f"{2 * n} frames in {images}: {n} training images, then their night copies (shuffled); gt {args.out / 'gt.npy'}")


if __name__ == "__main__":
    main()
