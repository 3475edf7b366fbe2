"""Per-frame evidence of an evaluation run: one JSON line per frame, and match images of failures.

A frame's record says what the detector saw (keypoints, the top candidates with their FAB-MAP
probability and log-likelihood ratio, which of them were checked geometrically and how that
went), what it chose, and, with ground truth, whether that was right. Failure images show the
query beside the place it matched (false positives) or the true place it failed to verify
(misses whose true place was a candidate), with the inlier pairs as lines.
"""

from __future__ import annotations

import json
from collections.abc import Iterator, Sequence
from pathlib import Path

import cv2
import numpy as np

from aefabmap_runtime.errors import InputError
from aefabmap_runtime.adapters.frames import load_image
from aefabmap_runtime.core.records.messages import Candidate, FrameResult
from aefabmap_runtime.core.verify.verification import VerificationConfig
from aefabmap_runtime.tools.pr_metrics import correct_predictions

#: evidence of a frame: too few keypoints to verify anything / nothing was checked (empty map,
#: verification off) / candidates were checked and none passed / a candidate was verified.
EVIDENCE = ("none", "unchecked", "rejected", "verified")
#: verified outcome of a frame against ground truth (tolerant).
OUTCOMES = ("true_positive", "false_positive", "miss", "true_negative")
#: why a missed revisit was not verified, from the most significant check of its true place:
#: no true place among the candidates / one was a candidate but not checked / checked, no model
#: fitted / log10 NFA >= 0 (no geometric evidence) / between the bar and 0 / below the bar but
#: rejected for another reason (conditioning, cheirality, temporal check).
MISS_REASONS = ("not_a_candidate", "unchecked", "no_model", "nfa_at_least_0", "nfa_below_0", "rejected_other")


def min_evidence_keypoints(config: VerificationConfig) -> int:
    """Fewest keypoints a frame needs for any geometric model to pass (the smaller inlier bar)."""
    return int(min(config.min_inliers, config.min_inliers_h))


def _candidate_doc(c: Candidate) -> dict:
    """JSON form of a candidate (the inlier point pairs stay out: they go into the images)."""
    return {
        "place": c.place,
        "frame": c.frame,
        "rank": c.rank,
        "probability": c.probability,
        "llr": c.llr,
        "similarity": c.similarity,
        "checked": c.checked,
        "source": c.source,
        "verified": c.verified,
        "inliers": c.inliers,
        "matches": c.matches,
        "model": c.model,
        "nfa": c.nfa,
    }


def evidence_of(res: FrameResult, min_keypoints: int) -> str:
    """One of EVIDENCE for a frame result."""
    if res.n_keypoints < min_keypoints:
        return "none"
    if res.verified:
        return "verified"
    if not any(c.checked for c in res.candidates):
        return "unchecked"
    return "rejected"


def _true_candidates(res: FrameResult, true_frames: np.ndarray, tolerance: int) -> list[Candidate]:
    """The candidates within `tolerance` frames of a true match."""
    if true_frames.size == 0:
        return []
    return [c for c in res.candidates if np.any(np.abs(true_frames - c.frame) <= tolerance)]


def _true_candidate(res: FrameResult, true_frames: np.ndarray, tolerance: int) -> Candidate | None:
    """The candidate within `tolerance` frames of a true match: the checked one with most inliers first."""
    hits = _true_candidates(res, true_frames, tolerance)
    return max(hits, key=lambda c: (c.checked, c.inliers, -c.rank)) if hits else None


def miss_reason(res: FrameResult, true_frames: np.ndarray, tolerance: int, max_log10_nfa: float) -> str:
    """One of MISS_REASONS for a revisit frame that was not verified to a true place."""
    hits = _true_candidates(res, true_frames, tolerance)
    if not hits:
        return "not_a_candidate"
    checked = [c for c in hits if c.checked]
    if not checked:
        return "unchecked"
    nfas = [c.nfa for c in checked if c.nfa is not None]
    if not nfas:
        return "no_model"
    best = min(nfas)
    if best >= 0:
        return "nfa_at_least_0"
    return "nfa_below_0" if best >= max_log10_nfa else "rejected_other"


def frame_records(
    results: Sequence[FrameResult],
    gt: np.ndarray | None,
    tolerance: int,
    min_keypoints: int,
    max_log10_nfa: float = VerificationConfig.max_log10_nfa,
) -> Iterator[dict]:
    """One JSON-able dict per frame (see the module docstring); gt: (N, N) bool or None;
    max_log10_nfa: the run's acceptance bar (the NFA bands of `miss_reason`)."""
    n = len(results)
    correct = {}
    if gt is not None:
        if gt.shape != (n, n):
            raise InputError(f"ground truth has shape {gt.shape}, expected ({n}, {n})")
        gt = np.tril(np.asarray(gt, bool), k=-1)
        raw = np.array([-1 if r.best_frame is None else r.best_frame for r in results], np.int64)
        chosen = np.array([r.verified_frame if r.verified and r.verified_frame is not None else -1 for r in results], np.int64)
        for name, pred in (("raw", raw), ("verified", chosen)):
            correct[f"{name}_strict"] = correct_predictions(pred, gt, 0)
            correct[f"{name}_tolerant"] = correct_predictions(pred, gt, tolerance)
    for i, r in enumerate(results):
        doc = {
            "frame": i,
            "n_keypoints": r.n_keypoints,
            "n_words": r.n_words,
            "evidence": evidence_of(r, min_keypoints),
            "raw_frame": r.best_frame,
            "raw_score": r.score,
            "probability": r.probability,
            "llr": r.llr,
            "candidates": [_candidate_doc(c) for c in r.candidates],
            "candidates_tried": r.candidates_tried,
            "verified": r.verified,
            "chosen_frame": r.verified_frame if r.verified else None,
            "inliers": r.inliers,
            "matches": r.matches,
            "geometry_model": r.geometry_model,
            "nfa": getattr(r, "nfa", None),
        }
        if gt is not None:
            true_frames = np.flatnonzero(gt[i])
            doc["true_loop"] = bool(true_frames.size)
            doc["true_frames"] = true_frames.tolist()
            # None where that output made no prediction for this frame.
            predicted = {"raw": r.best_frame is not None, "verified": r.verified}
            doc["correct"] = {k: bool(v[i]) if predicted[k.split("_")[0]] else None for k, v in correct.items()}
            doc["true_place_candidate"] = _true_candidate(r, true_frames, tolerance) is not None
            doc["outcome"] = _outcome(r.verified, bool(correct["verified_tolerant"][i]), bool(true_frames.size))
            if doc["outcome"] == "miss":
                doc["miss_reason"] = miss_reason(r, true_frames, tolerance, max_log10_nfa)
        yield doc


def revisit_split(records: Sequence[dict]) -> dict:
    """Where recall is lost, over the revisit frames (ground truth has a true place) of
    `frame_records`: verified to a true place, to a wrong one, true place among the checked
    candidates, and each miss by MISS_REASONS."""
    revisits = [d for d in records if d.get("true_loop")]
    misses = [d for d in revisits if d.get("outcome") == "miss"]
    return {
        "revisits": len(revisits),
        "verified": sum(d["outcome"] == "true_positive" for d in revisits),
        "wrong_place": sum(d["outcome"] == "false_positive" for d in revisits),
        "true_place_checked": sum(bool(d.get("true_place_candidate")) and d.get("miss_reason") != "unchecked"
                                  for d in revisits),
        "misses": {reason: sum(d.get("miss_reason") == reason for d in misses) for reason in MISS_REASONS},
    }


def format_revisit_split(split: dict) -> str:
    """One line for the printed evaluation."""
    n = split["revisits"]
    misses = ", ".join(f"{k} {v}" for k, v in split["misses"].items() if v)
    return (f"revisit frames {n}: verified {split['verified']}, wrong place {split['wrong_place']}, "
            f"true place among the checked candidates {split['true_place_checked']}; misses: {misses or 'none'}")


def _outcome(verified: bool, right: bool, true_loop: bool) -> str:
    if verified:
        return "true_positive" if right else "false_positive"
    return "miss" if true_loop else "true_negative"


def write_frames_jsonl(path: str | Path, records) -> int:
    """Write records as JSON lines; returns how many were written."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    count = 0
    with path.open("w") as f:
        for doc in records:
            f.write(json.dumps(doc, separators=(",", ":")) + "\n")
            count += 1
    return count


def failure_cases(results: Sequence[FrameResult], records: Sequence[dict], tolerance: int) -> list[tuple[int, str, Candidate | None]]:
    """(frame, "false_positive" | "miss", candidate to draw) for every false positive and every
    miss whose true place was among the candidates. A false positive draws the verified place."""
    cases = []
    for r, doc in zip(results, records):
        outcome = doc.get("outcome")
        if outcome == "false_positive":
            chosen = next((c for c in r.candidates if c.verified and c.frame == r.verified_frame), None)
            cases.append((doc["frame"], outcome, chosen))
        elif outcome == "miss" and doc["true_place_candidate"]:
            cases.append((doc["frame"], outcome, _true_candidate(r, np.asarray(doc["true_frames"]), tolerance)))
    return cases


#: failure images narrower than this are scaled up (small-board cameras give 160 px frames,
#: too small to read the caption or see the lines).
MIN_IMAGE_WIDTH = 640


def match_image(query: np.ndarray, place: np.ndarray, points: np.ndarray | None, caption: str, colour: tuple[int, int, int]) -> np.ndarray:
    """Query (left) beside place (right), inlier pairs (K, 4) (x_q, y_q, x_p, y_p) as lines, caption on top.

    The pair is scaled up by an integer factor until it is at least MIN_IMAGE_WIDTH px wide.
    """
    scale = max(1, -(-MIN_IMAGE_WIDTH // (query.shape[1] + place.shape[1])))
    q, p = (cv2.resize(im, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST) if scale > 1 else im for im in (query, place))
    q = cv2.cvtColor(q, cv2.COLOR_GRAY2BGR) if q.ndim == 2 else q
    p = cv2.cvtColor(p, cv2.COLOR_GRAY2BGR) if p.ndim == 2 else p
    h = max(q.shape[0], p.shape[0])
    band = 22
    canvas = np.zeros((h + band, q.shape[1] + p.shape[1], 3), np.uint8)
    canvas[band : band + q.shape[0], : q.shape[1]] = q
    canvas[band : band + p.shape[0], q.shape[1] :] = p
    if points is not None:
        # Pixel centres: x in the original image is at (x + 0.5) * scale - 0.5 in the scaled one.
        xy = np.rint((np.asarray(points, np.float64) + 0.5) * scale - 0.5).astype(int)
        for xq, yq, xp, yp in xy.tolist():
            a = (xq, yq + band)
            b = (xp + q.shape[1], yp + band)
            cv2.line(canvas, a, b, colour, 1, cv2.LINE_AA)
            cv2.circle(canvas, a, 2, colour, -1, cv2.LINE_AA)
            cv2.circle(canvas, b, 2, colour, -1, cv2.LINE_AA)
    cv2.putText(canvas, caption, (4, 15), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (255, 255, 255), 1, cv2.LINE_AA)
    return canvas


def write_failure_images(out_dir: str | Path, images: Sequence[Path], cases) -> list[Path]:
    """One PNG per failure case: `<frame>_<kind>_<place frame>.png`; returns the paths written."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for frame, kind, cand in cases:
        if cand is None:
            continue  # a verified frame always has its candidate among res.candidates
        query = load_image(images[frame])
        place = load_image(images[cand.frame])
        what = "FALSE POSITIVE" if kind == "false_positive" else "MISS"
        check = f"{cand.model or '-'} {cand.inliers} inl / {cand.matches} m" if cand.checked else "not checked"
        nfa = f" nfa {cand.nfa:.2g}" if cand.nfa is not None else ""
        caption = f"{what}: frame {frame} vs {cand.frame} (rank {cand.rank}, {check}{nfa})"
        colour = (0, 0, 255) if kind == "false_positive" else (0, 200, 255)
        img = match_image(query, place, cand.inlier_points, caption, colour)
        path = out_dir / f"{frame:06d}_{kind}_{cand.frame:06d}.png"
        if not cv2.imwrite(str(path), img):
            raise InputError(f"could not write image {path}")
        written.append(path)
    return written
