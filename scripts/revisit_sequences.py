#!/usr/bin/env python
"""Revisit sequences from TRAINING drives only, to measure candidate and verification policies.

Each CamVid drive becomes one sequence: a first pass that plays every `step`-th frame, then a
second pass of the frames halfway between them, so that every second-pass frame revisits the two
first-pass frames `step / 2` drive frames away, and nothing else. The larger the step, the
larger the viewpoint change of each revisit (step 4: gap 2, where training pairs mostly verify;
step 6: gap 3, where about half do). First-pass frames are never revisits, so a loop published
among them, even to structure further down the same street, is a wrong one. With `--night` the
second pass is seen at the fixed synthetic night of the vocabulary's test pairs
(trainer/aefabmap_trainer/multiview.NIGHT, its noise seeded by the frame): a day map revisited at night.

    python scripts/revisit_sequences.py --data DATA --out revisits --step 6 [--night]
    aefabmap eval --model BUNDLE --images revisits/0001TP/images --gt revisits/0001TP/gt.npy \\
        --exclude 10 --tolerance 1 --fabmap-score llr
"""

from __future__ import annotations

import argparse
import os
import shutil
from pathlib import Path

import cv2
import numpy as np
from calibrate_sequence import drives  # the training drives, one list of frames each

from aefabmap_trainer.multiview import NIGHT, darken


def revisit_order(n_frames: int, step: int) -> tuple[list[int], np.ndarray]:
    """Drive frame indices in sequence order (first pass, then second pass) and the (N, N) bool
    ground truth: gt[i, j] when sequence frame i revisits the earlier sequence frame j."""
    if step < 2 or step % 2:
        raise ValueError(f"step must be even and >= 2, got {step}")
    first = list(range(0, n_frames, step))
    second = list(range(step // 2, n_frames, step))
    order = first + second
    gt = np.zeros((len(order), len(order)), bool)
    for j in range(len(second)):
        for k in (j, j + 1):  # the first-pass frames step/2 before and after
            if k < len(first):
                gt[len(first) + j, k] = True
    return order, gt


def write_sequence(frames: list[Path], step: int, out: Path, night: bool = False) -> int:
    """Copy one drive's frames to out/images in revisit order and save out/gt.npy; frames written.
    night: second-pass frames are written as grey PNGs at the synthetic NIGHT (noise seeded by
    the sequence frame number, so a run repeats exactly)."""
    order, gt = revisit_order(len(frames), step)
    images = out / "images"
    images.mkdir(parents=True, exist_ok=True)
    revisits = gt.any(axis=1)  # the second pass: every frame of it revisits the first
    for i, f in enumerate(order):
        if night and revisits[i]:
            gray = cv2.imread(str(frames[f]), cv2.IMREAD_GRAYSCALE)
            if gray is None:
                raise SystemExit(f"cannot read {frames[f]}")
            cv2.imwrite(str(images / f"{i:05d}.png"), darken(gray, np.random.default_rng(i), **NIGHT))
        else:
            shutil.copyfile(frames[f], images / f"{i:05d}{frames[f].suffix.lower()}")
    np.save(out / "gt.npy", gt)
    return len(order)


def main(argv: list[str] | None = None) -> None:
    repo = Path(__file__).resolve().parents[1]
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=Path(os.environ.get("AEFABMAP_DATA", repo.parent / "shared" / "data")))
    ap.add_argument("--out", type=Path, required=True, help="folder for one DRIVE/images + DRIVE/gt.npy per drive")
    ap.add_argument("--step", type=int, default=6, help="first pass plays every STEP-th frame (even; revisit gap STEP/2)")
    ap.add_argument("--night", action="store_true", help="the second pass at the synthetic night")
    args = ap.parse_args(argv)
    camvid = args.data / "train" / "camvid"
    if not camvid.is_dir():
        raise SystemExit(f"no CamVid training drives under {camvid}")
    for name, frames in drives(camvid).items():
        n = write_sequence(frames, args.step, args.out / name, args.night)
        print(f"{name}: {n} frames -> {args.out / name}")


if __name__ == "__main__":
    main()
