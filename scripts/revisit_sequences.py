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
With `--reverse` the second pass is played backwards, a route driven back, after `GAP` first-pass
frames of the next drive (in name order) that nothing revisits: they put every revisit beyond the
eval's 15-frame exclusion window (without them the first backward frames would revisit frames
inside it). A frame is darkened the same way either way.

    python scripts/revisit_sequences.py --data DATA --out revisits --step 6 [--night] [--reverse]
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


#: Frames of another drive between the passes of a reversed sequence (module docstring).
GAP = 16


def revisit_order(n_frames: int, step: int, reverse: bool = False,
                  gap: int = 0) -> tuple[list[int | None], np.ndarray]:
    """Drive frame indices in sequence order (first pass, `gap` slots (None) for frames of another
    drive, then the second pass, backwards when `reverse`) and the (N, N) bool ground truth:
    gt[i, j] when sequence frame i revisits the earlier sequence frame j."""
    if step < 2 or step % 2:
        raise ValueError(f"step must be even and >= 2, got {step}")
    first = list(range(0, n_frames, step))
    second = list(range(step // 2, n_frames, step))
    passes = list(range(len(second)))[::-1] if reverse else list(range(len(second)))
    order = [*first, *[None] * gap, *(second[j] for j in passes)]
    gt = np.zeros((len(order), len(order)), bool)
    start = len(first) + gap
    for i, j in enumerate(passes):
        for k in (j, j + 1):  # the first-pass frames step/2 before and after
            if k < len(first):
                gt[start + i, k] = True
    return order, gt


def filler(by_drive: dict[str, list[Path]], drive: str, step: int) -> list[Path]:
    """`GAP` first-pass frames of the drives after `drive` (in name order, wrapping round): the
    next drive's, then the one after it, as far as needed."""
    names = sorted(by_drive)
    start = names.index(drive)
    others = [by_drive[names[(start + k) % len(names)]][::step] for k in range(1, len(names))]
    frames = [f for first_pass in others for f in first_pass][:GAP]
    if len(frames) < GAP:
        raise SystemExit(f"--reverse needs {GAP} first-pass frames of other CamVid drives to play between the "
                         f"passes of {drive}; they hold {len(frames)}")
    return frames


def write_sequence(frames: list[Path], step: int, out: Path, night: bool = False,
                   between: list[Path] | None = None) -> int:
    """Copy one drive's frames to out/images in revisit order and save out/gt.npy; frames written.
    night: second-pass frames are written as grey PNGs at the synthetic NIGHT (noise seeded by
    the frame's place in the forward sequence, so a run repeats exactly and a frame is darkened
    alike either way). between: frames of another drive played between the passes, the second
    pass then backwards (`filler`); None plays it forwards."""
    reverse = between is not None
    order, gt = revisit_order(len(frames), step, reverse, len(between or []))
    forward = {f: i for i, f in enumerate(revisit_order(len(frames), step)[0])}
    images = out / "images"
    images.mkdir(parents=True, exist_ok=True)
    revisits = gt.any(axis=1)  # the second pass: every frame of it revisits the first
    fill = iter(between or [])
    for i, f in enumerate(order):
        if f is None:
            src = next(fill)
            shutil.copyfile(src, images / f"{i:05d}{src.suffix.lower()}")
        elif night and revisits[i]:
            gray = cv2.imread(str(frames[f]), cv2.IMREAD_GRAYSCALE)
            if gray is None:
                raise SystemExit(f"cannot read {frames[f]}")
            cv2.imwrite(str(images / f"{i:05d}.png"), darken(gray, np.random.default_rng(forward[f]), **NIGHT))
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
    ap.add_argument("--reverse", action="store_true",
                    help=f"the second pass backwards (a route driven back), after {GAP} frames of the next drive")
    args = ap.parse_args(argv)
    camvid = args.data / "train" / "camvid"
    if not camvid.is_dir():
        raise SystemExit(f"no CamVid training drives under {camvid}")
    by_drive = drives(camvid)
    for name, frames in by_drive.items():
        between = filler(by_drive, name, args.step) if args.reverse else None
        n = write_sequence(frames, args.step, args.out / name, args.night, between)
        print(f"{name}: {n} frames -> {args.out / name}")


if __name__ == "__main__":
    main()
