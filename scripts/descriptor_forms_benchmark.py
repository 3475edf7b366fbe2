#!/usr/bin/env python
"""CPU time of the learned descriptor's compiled forms, per 1000 keypoints and orientation.

Each form of `native.learned_describe` (native.LEARNED_FORMS; a form the CPU lacks gives way to
the next one it runs) describes the same ORB keypoints of the same frames; the bytes of every form
are first compared with the numpy form's. Run it pinned to one core:

    taskset -c 1 python scripts/descriptor_forms_benchmark.py --model BUNDLE --images DATA/lip6_outdoor \\
        --json forms.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from aefabmap_runtime.adapters.bundle_reader import load_bundle
from aefabmap_runtime.core.features.learned_description import LearnedDescription
from aefabmap_runtime.core.features.orb_description import blurred, pyramid
from aefabmap_runtime.core.kernels import native
from aefabmap_runtime.errors import AefabmapError

#: The keypoints described per frame, the frame's long side (px) and ORB's pyramid.
KEYPOINTS, LONG_SIDE, LEVELS, SCALE = 1000, 512, 8, 1.2


def prepared(gray: np.ndarray) -> tuple[list[np.ndarray], np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """ORB's keypoints of a grey frame scaled to LONG_SIDE and the blurred pyramid they are
    described on: levels, 1 / scales (L,), xy (N, 2), angle (N,) degrees, octave (N,)."""
    scale = LONG_SIDE / max(gray.shape)
    gray = cv2.resize(gray, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR)
    keypoints = cv2.ORB_create(KEYPOINTS, SCALE, LEVELS).detect(gray, None)
    levels, inv = pyramid(gray, LEVELS, SCALE)
    return (blurred(levels), inv, np.array([k.pt for k in keypoints], np.float32).reshape(-1, 2),
            np.array([k.angle for k in keypoints], np.float32), np.array([k.octave for k in keypoints], np.int32))


def time_forms(description: LearnedDescription, frames: list, repeats: int) -> dict:
    """Per form: CPU ms per 1000 keypoints (one orientation) over `frames` (as `prepared` returns),
    each described `repeats` times, and whether every frame's bytes equal numpy's."""
    keypoints = sum(len(f[3]) for f in frames)
    result = {"keypoints": keypoints, "repeats": repeats, "forms": {}}
    for form in native.LEARNED_FORMS:
        same = all(np.array_equal(description.describe(*f, compiled=True, form=form),
                                  description.describe(*f, compiled=False)) for f in frames)
        start = time.process_time()
        for _ in range(repeats):
            for f in frames:
                description.describe(*f, compiled=True, form=form)
        ms = (time.process_time() - start) * 1e3 / repeats / max(keypoints, 1) * 1000
        result["forms"][form] = {"ms_per_1000_keypoints": round(ms, 3), "same_bytes_as_numpy": same}
    return result


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", required=True, help="a bundle trained with --descriptor learned")
    ap.add_argument("--images", required=True, help="a folder of frames (every --every-th is used)")
    ap.add_argument("--every", type=int, default=60)
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--json", help="write the figures here")
    args = ap.parse_args(argv)
    if not native.available():
        print("the compiled kernels are not built here", file=sys.stderr)
        return 1
    try:
        description = load_bundle(args.model).learned_description
    except AefabmapError as e:
        print(e, file=sys.stderr)
        return 1
    if description is None:
        print(f"{args.model}: not a learned-descriptor bundle", file=sys.stderr)
        return 1
    paths = sorted(p for p in Path(args.images).iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png"))
    grays = [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in paths[:: max(args.every, 1)]]
    frames = [prepared(g) for g in grays if g is not None]
    if not frames:
        print(f"{args.images}: no readable frame", file=sys.stderr)
        return 1
    result = time_forms(description, frames, args.repeats)
    result.update(model=str(args.model), images=str(args.images), frames=len(frames))
    for form, figures in result["forms"].items():
        print(f"{form:>13}: {figures['ms_per_1000_keypoints']:7.2f} ms per 1000 keypoints and orientation"
              f"{'' if figures['same_bytes_as_numpy'] else '  (bytes differ from numpy!)'}")
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2) + "\n")
    return 0 if all(f["same_bytes_as_numpy"] for f in result["forms"].values()) else 1


if __name__ == "__main__":
    sys.exit(main())
