#!/usr/bin/env python
"""Which feature front-end verifies the most true pairs, on TRAINING images only (never Lip6 or validation).

Pairs, all from DATA/train:
- CamVid frames of one drive 1, 2, 3, 5 and 10 frames apart, and the unrelated negatives
  (other drives, Scene-15, CamVid vs Scene-15), both from `calibrate_verification.training_pairs`;
- synthetic viewpoint changes: a CamVid or Scene-15 image against itself seen from a camera
  turned 10/20/30/40 degrees about the vertical axis of the (planar) scene;
- synthetic scale changes: the same image resized 0.5/0.75/1.5/2 times about its centre, in a
  canvas of the original size (cropped or padded with black).

With `--night`, the second image of every pair (negatives included) is seen at the fixed
synthetic night of the vocabulary's test pairs (trainer/aefabmap_trainer/multiview.NIGHT: darker, gamma, sensor
noise, blur): a day map revisited at night, under the same viewpoint and scale changes.

Each pair is verified as the runtime's brute-force retry verifies a loop candidate (no words:
all descriptors matched with the ratio test, then the a-contrario test), and each front-end
gets a row: the share of true pairs accepted per setting, the negatives accepted (must stay 0),
the lowest log10 NFA of a negative (how close the nearest unrelated pair came to the -4 bar),
and the median milliseconds of one extraction and of one pair's verification.

    python scripts/pair_benchmark.py orb orb-teblid akaze sift --per-drive 6 --warps-per-setting 24 \
        --long-side 160 --json pairs_160.json
    python scripts/pair_benchmark.py orb orb-stretch --per-drive 6 --night --json pairs_night.json
    python scripts/pair_benchmark.py orb-stretch-upright orb-learned --learned BUNDLE --night
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import math
import os
import random
import sys
import time
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
from calibrate_verification import GAPS, training_pairs  # noqa: E402

from aefabmap_runtime.adapters.bundle_reader import load_bundle  # noqa: E402
from aefabmap_runtime.adapters.frames import load_image  # noqa: E402
from aefabmap_runtime.core.verify import verification as V  # noqa: E402
from aefabmap_runtime.core.features.features import FeatureConfig, FeatureExtractor, Features  # noqa: E402
from aefabmap_trainer.multiview import NIGHT, darken  # noqa: E402

ANGLES = (10, 20, 30, 40)  # degrees of out-of-plane rotation
SCALES = (0.5, 0.75, 1.5, 2.0)
KEYPOINTS = 1000  # the runtime's verification budget (VerificationConfig.keypoints)
FRONT_ENDS = ("orb", "orb-teblid", "orb-beblid", "akaze", "sift", "orb-native", "orb-levels12", "orb-fast10", "orb-fast5", "orb-clahe", "orb-stretch",
              "orb-stretch-upright", "orb-learned")
#: AKAZE's detector threshold: OpenCV's default (0.001) finds 200-1300 keypoints on 640-px CamVid
#: frames, so the 1000-keypoint cap would rarely bind; at 0.0001 it finds 1000-4500.
AKAZE_THRESHOLD = 1e-4
#: Radius of AKAZE's MLDB window in keypoint sizes: its grid spans +-10 units of 0.5 size
#: (OpenCV's AKAZEFeatures.cpp), rotated: 5 * sqrt(2) (the convention of SIFT's 5.3 in feature_kinds.py).
AKAZE_WINDOW_SCALE = 5 * math.sqrt(2)


class Unavailable(RuntimeError):
    """A front-end this OpenCV build cannot run (e.g. no contrib module)."""


class DetectThenDescribe:
    """A Feature2D stand-in: keypoints from `detector`, descriptors from `descriptor`."""

    def __init__(self, detector, descriptor) -> None:
        self.detector, self.descriptor = detector, descriptor

    def detectAndCompute(self, image, mask):  # noqa: N802 - OpenCV's name
        return self.descriptor.compute(image, self.detector.detect(image, mask))


@dataclass(frozen=True)
class FrontEnd:
    """A feature extractor and how its descriptors compare.

    distance: "hamming" (binary) or "l2" (unit-norm floats). window_scale: descriptor window
    radius in keypoint sizes (FeatureKind.window_scale), for the independence radius.
    """

    name: str
    extractor: FeatureExtractor
    distance: str
    window_scale: float


def make_front_end(name: str, learned: Path | None = None) -> FrontEnd:
    """The front-end called `name` (one of FRONT_ENDS); Unavailable when OpenCV lacks it, or for
    orb-learned (the runtime's default ORB with a bundle's learned descriptor) without `learned`,
    the bundle.

    All run through the runtime's FeatureExtractor (resizing to its 640-px long side unless
    stated, strongest KEYPOINTS kept, positions mapped back to original pixels); the others
    swap its OpenCV detector for their own.
    """
    if name == "sift":
        ex = FeatureExtractor(FeatureConfig(kind="sift", max_features=KEYPOINTS, rootsift=True))
        return FrontEnd(name, ex, "l2", ex.kind.window_scale)
    if name == "orb-learned":
        if learned is None:
            raise Unavailable("orb-learned needs --learned BUNDLE (a bundle trained with --descriptor learned)")
        bundle = load_bundle(learned)
        if bundle.learned_description is None:
            raise Unavailable(f"{learned} has no learned descriptor")
        ex = FeatureExtractor(FeatureConfig(kind="orb", max_features=KEYPOINTS, long_side=640, contrast_stretch=True,
                                            descriptor="learned"), upright=True, learned=bundle.learned_description)
        return FrontEnd(name, ex, "hamming", ex.kind.window_scale)
    native = name == "orb-native"
    # orb-stretch-upright: the runtime's default (contrast stretch, the retry with upright descriptors).
    ex = FeatureExtractor(FeatureConfig(kind="orb", max_features=KEYPOINTS, long_side=None if native else 640,
                                        clahe=name == "orb-clahe", contrast_stretch=name.startswith("orb-stretch")),
                          upright=name == "orb-stretch-upright")
    window = ex.kind.window_scale
    if name in ("orb-teblid", "orb-beblid"):
        x2d = getattr(cv2, "xfeatures2d", None)
        if x2d is None:
            raise Unavailable(f"{name} needs cv2.xfeatures2d (opencv-contrib-python)")
        # 1.0: OpenCV's documented scale for ORB keypoints; 256 bits: ORB's descriptor size.
        describe = (x2d.TEBLID_create(1.0, x2d.TEBLID_SIZE_256_BITS) if name == "orb-teblid"
                    else x2d.BEBLID_create(1.0, x2d.BEBLID_SIZE_256_BITS))
        ex.replace_detector(DetectThenDescribe(ex._detector, describe))
    elif name == "akaze":
        ex.replace_detector(cv2.AKAZE_create(threshold=AKAZE_THRESHOLD))  # MLDB, 486 bits in 61 bytes
        window = AKAZE_WINDOW_SCALE
    elif name == "orb-levels12":
        ex.replace_detector(cv2.ORB_create(nfeatures=KEYPOINTS, nlevels=12))
    elif name.startswith("orb-fast"):
        ex.replace_detector(cv2.ORB_create(nfeatures=KEYPOINTS, fastThreshold=int(name[len("orb-fast"):])))
    elif name not in ("orb", "orb-native", "orb-clahe", "orb-stretch", "orb-stretch-upright") and not name.startswith("orb-fast"):
        raise ValueError(f"unknown front-end {name!r}; choose from {FRONT_ENDS}")
    return FrontEnd(name, ex, "hamming", window)


@dataclass(frozen=True)
class View:
    """One image of a pair: a file, optionally warped: ("rotate", degrees) or ("scale", factor),
    and optionally seen at night (NIGHT, after the warp)."""

    path: Path
    warp: tuple = ()
    night: bool = False


def rotation_homography(shape_hw: tuple[int, int], degrees: float) -> np.ndarray:
    """(3, 3) map of pixels of a fronto-parallel planar scene to its view from a camera turned
    `degrees` about the vertical axis through the image centre (orbiting at the plane's depth,
    so the centre stays put). Pinhole with focal length = image width (px), centred."""
    h, w = shape_hw
    K = np.array([[w, 0, (w - 1) / 2], [0, w, (h - 1) / 2], [0, 0, 1]], np.float64)
    t = math.radians(degrees)
    c, s = math.cos(t), math.sin(t)
    R = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])  # rows: the new camera's axes in scene coordinates
    centre = np.array([s, 0, 1 - c])  # the new camera's position, plane at depth 1
    # Scene point X = K^-1 u (depth 1); seen at K R (X - centre), and X_z = 1, so X - centre = (I - centre e3^T) X.
    return K @ R @ (np.eye(3) - np.outer(centre, [0, 0, 1])) @ np.linalg.inv(K)


def rotate_view(gray: np.ndarray, degrees: float) -> np.ndarray:
    """The image as seen after `rotation_homography`, same size, black outside the scene."""
    H = rotation_homography(gray.shape, degrees)
    return cv2.warpPerspective(gray, H, gray.shape[::-1], flags=cv2.INTER_LINEAR, borderValue=0)


def scale_about_centre(gray: np.ndarray, factor: float) -> np.ndarray:
    """The image resized `factor` times about its centre, cropped or black-padded to its own size."""
    h, w = gray.shape
    interp = cv2.INTER_AREA if factor < 1 else cv2.INTER_LINEAR
    small = cv2.resize(gray, (max(1, round(w * factor)), max(1, round(h * factor))), interpolation=interp)
    oy, ox = (h - small.shape[0]) // 2, (w - small.shape[1]) // 2  # small's origin in the canvas
    y0, x0, y1, x1 = max(0, oy), max(0, ox), min(h, oy + small.shape[0]), min(w, ox + small.shape[1])
    out = np.zeros_like(gray)
    out[y0:y1, x0:x1] = small[y0 - oy:y1 - oy, x0 - ox:x1 - ox]
    return out


def shrink(gray: np.ndarray, long_side: int | None) -> np.ndarray:
    """The image downsized (INTER_AREA) so its longer side is `long_side` px; smaller ones and None: unchanged."""
    if long_side is None or max(gray.shape) <= long_side:
        return gray
    s = long_side / max(gray.shape)
    return cv2.resize(gray, (max(1, round(gray.shape[1] * s)), max(1, round(gray.shape[0] * s))),
                      interpolation=cv2.INTER_AREA)


def render(view: View, long_side: int | None) -> np.ndarray:
    """The grayscale uint8 pixels of a view: loaded, shrunk to `long_side`, warped, then darkened
    (the night's noise seeded by the view, so a view renders the same every time)."""
    gray = shrink(load_image(view.path), long_side)
    if view.warp:
        how, amount = view.warp
        gray = rotate_view(gray, amount) if how == "rotate" else scale_about_centre(gray, amount)
    if view.night:
        seed = int(hashlib.sha256(repr((view.path.name, view.warp)).encode()).hexdigest()[:8], 16)
        gray = darken(gray, np.random.default_rng(seed), **NIGHT)
    return gray


def benchmark_pairs(train: Path, seed: int, per_drive: int, warps_per_setting: int, night: bool = False) -> list[tuple]:
    """(group, setting, View a, View b) rows: group "gap" (setting: frames apart), "angle" (degrees),
    "scale" (factor) or "negative" (setting None). Warps use the same `warps_per_setting` source
    images in every setting (half CamVid, half Scene-15, drawn with `seed`); the rotation's
    direction alternates from image to image. `night`: every View b is seen at night."""
    pos, neg = training_pairs(train, seed=seed, per_drive=per_drive)
    rows = [("gap", gap, View(a), View(b)) for gap in GAPS for a, b in pos[gap]]
    rng = random.Random(seed)
    camvid = sorted((train / "camvid").glob("*.jpg"))
    scenes = sorted((train / "scene15").rglob("*.jpg"))
    n_camvid = (warps_per_setting + 1) // 2
    sources = rng.sample(camvid, n_camvid) + rng.sample(scenes, warps_per_setting - n_camvid)
    for i, p in enumerate(sources):
        rows += [("angle", a, View(p), View(p, ("rotate", a if i % 2 == 0 else -a))) for a in ANGLES]
        rows += [("scale", s, View(p), View(p, ("scale", s))) for s in SCALES]
    rows += [("negative", None, View(a), View(b)) for a, b in neg]
    if night:
        rows = [(g, s, a, dataclasses.replace(b, night=True)) for g, s, a, b in rows]
    return rows


def verify(fa: Features, fb: Features, front: FrontEnd, config: V.VerificationConfig) -> V.GeometryResult:
    """Verify a pair as the runtime's brute-force retry does (no words: all-pairs matching, then
    upright descriptors where the front-end has them), as calibrate_verification.py does, with the
    front-end's distance and descriptor window."""
    none_a, none_b = np.full(len(fa), V.NO_WORD, np.int64), np.full(len(fb), V.NO_WORD, np.int64)
    cv2.setRNGSeed(0)  # USAC's sampling: the same pairs give the same verdicts
    radius = V.independence_radius(np.asarray(fa.sizes, np.float64) * front.window_scale, config)
    return V.verify_pair(fa.keypoints, none_a, fa.descriptors, fa.image_shape, fb.keypoints, none_b,
                         fb.descriptors, fb.image_shape, config, bruteforce=True, distance=front.distance,
                         radius=radius, q_upright=fa.upright, p_upright=fb.upright)


def measure(front: FrontEnd, rows: list[tuple], long_side: int | None) -> dict:
    """Run one front-end over all pairs -> its summary (see `summarise`)."""
    config = V.VerificationConfig()
    cache: dict[View, Features] = {}
    extract_ms, verify_ms, outcomes = [], [], []

    def features(view: View) -> Features:
        if view not in cache:
            gray = render(view, long_side)
            t0 = time.perf_counter()
            cache[view] = front.extractor.extract(gray)
            extract_ms.append(1e3 * (time.perf_counter() - t0))
        return cache[view]

    for group, setting, a, b in tqdm(rows, desc=front.name, unit="pair", leave=False):
        fa, fb = features(a), features(b)
        t0 = time.perf_counter()
        res = verify(fa, fb, front, config)
        verify_ms.append(1e3 * (time.perf_counter() - t0))
        outcomes.append((group, setting, res.verified, res.nfa))
    keypoints = [len(f) for f in cache.values()]
    return summarise(outcomes, extract_ms, verify_ms, keypoints)


def summarise(outcomes: list[tuple], extract_ms: list[float], verify_ms: list[float], keypoints: list[int]) -> dict:
    """Acceptance % per setting of each true-pair group, negatives accepted / total, lowest
    negative log10 NFA, median keypoints per image, median ms per extraction and per pair."""
    accepted = defaultdict(list)
    for group, setting, ok, _ in outcomes:
        accepted[(group, setting)].append(ok)
    negatives = [(ok, nfa) for group, _, ok, nfa in outcomes if group == "negative"]
    share = {g: {str(s): 100.0 * float(np.mean(v)) for (gg, s), v in accepted.items() if gg == g}
             for g in ("gap", "angle", "scale")}
    return {
        **share,
        "pairs_per_setting": {g: len(v) for (g, s), v in accepted.items() if g != "negative"},
        "negatives_accepted": int(sum(ok for ok, _ in negatives)),
        "negatives": len(negatives),
        "lowest_negative_log10_nfa": float(min((nfa for _, nfa in negatives), default=float("inf"))),
        "median_keypoints": float(np.median(keypoints)),
        "extract_ms": float(np.median(extract_ms)),
        "verify_ms": float(np.median(verify_ms)),
    }


def table(results: dict[str, dict]) -> str:
    """Markdown table of `summarise` results, one row per front-end."""
    head = (["front-end"] + [f"gap {g}" for g in GAPS] + [f"{a} deg" for a in ANGLES] + [f"x{s:g}" for s in SCALES]
            + ["neg accepted", "lowest neg log10 NFA", "keypoints", "extract ms", "verify ms/pair"])
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, r in results.items():
        cells = ([name] + [f"{r['gap'][str(g)]:.0f}%" for g in GAPS] + [f"{r['angle'][str(a)]:.0f}%" for a in ANGLES]
                 + [f"{r['scale'][str(s)]:.0f}%" for s in SCALES]
                 + [f"{r['negatives_accepted']} of {r['negatives']}", f"{r['lowest_negative_log10_nfa']:.1f}",
                    f"{r['median_keypoints']:.0f}", f"{r['extract_ms']:.1f}", f"{r['verify_ms']:.1f}"])
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    repo = Path(__file__).resolve().parents[1]
    ap.add_argument("front_ends", nargs="+", choices=FRONT_ENDS, metavar="FRONT_END",
                    help=f"front-ends to compare: {', '.join(FRONT_ENDS)}")
    ap.add_argument("--data", type=Path, default=Path(os.environ.get("AEFABMAP_DATA", repo.parent / "shared" / "data")),
                    help="data root with train/ (default: $AEFABMAP_DATA, else shared/data beside the checkout)")
    ap.add_argument("--per-drive", type=int, default=12, help="CamVid start frames per drive, one pair per gap each")
    ap.add_argument("--warps-per-setting", type=int, default=24, help="source images warped at every angle and scale")
    ap.add_argument("--long-side", type=int, default=None,
                    help="downsize every image to this long side (px) before anything (default: as stored)")
    ap.add_argument("--night", action="store_true",
                    help="the second image of every pair at the synthetic night (trainer/aefabmap_trainer/multiview.NIGHT)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--learned", type=Path, metavar="BUNDLE", help="orb-learned: the bundle whose learned descriptor to use")
    ap.add_argument("--json", type=Path, help="also write the numbers here")
    args = ap.parse_args(argv)
    rows = benchmark_pairs(args.data / "train", args.seed, args.per_drive, args.warps_per_setting, args.night)
    results, seconds = {}, {}
    for name in args.front_ends:
        try:
            front = make_front_end(name, args.learned)
        except Unavailable as exc:
            print(f"skipped {name}: {exc}", file=sys.stderr)
            continue
        t0 = time.perf_counter()
        results[name] = measure(front, rows, args.long_side)
        seconds[name] = time.perf_counter() - t0
        print(f"{name}: {seconds[name]:.0f} s", file=sys.stderr, flush=True)
    print(f"{len(rows)} pairs from {args.data / 'train'}, long side {args.long_side or 'as stored'}"
          f"{', second image at night' if args.night else ''}; "
          f"per setting: {next(iter(results.values()))['pairs_per_setting'] if results else {}}")
    print(table(results))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        meta = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()}
        args.json.write_text(json.dumps({"args": meta, "seconds": seconds, "results": results}, indent=1) + "\n")


if __name__ == "__main__":
    main()
