#!/usr/bin/env python
"""Chains of weak evidence between unrelated sequences, on TRAINING drives only (never Lip6 or validation).

Every ordered pair of CamVid drives (A, B) is run as one sequence: A's frames build the map, then
B's frames query it, so any chain ending at a B frame on a stored A frame is a false one. The
detector runs with chains off (single-pair verification as usual); each query's checked places
are fed to a SequenceEvidence whose bound is its link bound, so that every chain with any
evidence at all is seen. Printed per chain length: how many false chains formed and the lowest
summed log10 NFA among them (how close unrelated sequences came to `SequenceConfig.max_log10_nfa`),
plus single pairs of A and B the detector itself accepted (should be none).

    python scripts/calibrate_sequence.py --model BUNDLE --data DATA --frames 2 3 --json out.json
"""

from __future__ import annotations

import argparse
import json
import os
from dataclasses import replace
from pathlib import Path

from tqdm import tqdm

from aefabmap_runtime.adapters.bundle_reader import load_detector
from aefabmap_runtime.adapters.frames import load_image
from aefabmap_runtime.core.decide import candidates as C
from aefabmap_runtime.core.detector import DetectorConfig
from aefabmap_runtime.core.decide.sequence import Link, SequenceConfig, SequenceEvidence


def drives(camvid: Path) -> dict[str, list[Path]]:
    """CamVid images by drive (the file name's prefix before '_'), each in frame order."""
    out: dict[str, list[Path]] = {}
    for p in sorted(camvid.iterdir()):
        if p.suffix.lower() in (".png", ".jpg", ".jpeg"):
            out.setdefault(p.name.split("_")[0], []).append(p)
    return out


def checked_places(model: str, paths: list[Path], exclude: int) -> tuple[list[list[Link]], list[bool]]:
    """Run the detector (chains off) over paths -> per query its checked places as links, and
    whether a single pair verified it."""
    det = load_detector(model, DetectorConfig(exclude=exclude, fabmap_score="llr", sequence=SequenceConfig(frames=0)))
    links: list[list[Link]] = []
    search = C.CandidatePolicy.search

    def recording(policy, seq, top, ranking, place_frames, stored, check):
        s = search(policy, seq, top, ranking, place_frames, stored, check)
        links[-1] = [Link(a.place, int(place_frames[a.place]), float(a.result.nfa)) for a in s.attempts]
        return s

    verified = []
    C.CandidatePolicy.search = recording
    try:
        for p in paths:
            links.append([])
            verified.append(bool(det.process(load_image(p)).verified))
    finally:
        C.CandidatePolicy.search = search
    return links, verified


def false_chains(links: list[list[Link]], n_map: int, config: SequenceConfig) -> list[float]:
    """Summed log10 NFA of the best chain ending at each query after the first n_map frames whose
    last link is a map frame (every chain the link bound lets form)."""
    chain = SequenceEvidence(replace(config, max_log10_nfa=config.link_log10_nfa))
    out = []
    for t, query in enumerate(links):
        best = chain.update(query)
        if best is not None and t >= n_map and best[0].frame < n_map:
            out.append(best[1])
    return out


def main(argv: list[str] | None = None) -> None:
    repo = Path(__file__).resolve().parents[1]
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", required=True, help="model bundle directory")
    ap.add_argument("--data", type=Path, default=Path(os.environ.get("AEFABMAP_DATA", repo.parent / "shared" / "data")),
                    help="data root with train/camvid (default: $AEFABMAP_DATA, else shared/data beside the checkout)")
    ap.add_argument("--frames", type=int, nargs="+", default=[2, 3], help="chain lengths to report")
    ap.add_argument("--tolerance", type=int, default=SequenceConfig().tolerance)
    ap.add_argument("--exclude", type=int, default=20, help="exclusion window, frames")
    ap.add_argument("--json", type=Path, help="also write the numbers here")
    args = ap.parse_args(argv)
    by_drive = drives(args.data / "train" / "camvid")
    pairs = [(a, b) for a in by_drive for b in by_drive if a != b]
    sums: dict[int, list[float]] = {n: [] for n in args.frames}
    single = 0
    for a, b in tqdm(pairs, desc="drive pairs", unit="pair"):
        links, verified = checked_places(args.model, by_drive[a] + by_drive[b], args.exclude)
        n_map = len(by_drive[a])
        single += sum(v and any(x.frame < n_map for x in q if x.log10_nfa < -4) for v, q in
                      zip(verified[n_map:], links[n_map:]))
        for n in args.frames:
            sums[n] += false_chains(links, n_map, SequenceConfig(frames=n, tolerance=args.tolerance))
    report = {"drive_pairs": len(pairs), "single_pairs_accepted": single,
              "chains": {str(n): {"count": len(v), "lowest_log10_nfa": min(v, default=None)} for n, v in sums.items()},
              "bound": SequenceConfig().max_log10_nfa}
    print(json.dumps(report, indent=1))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=1) + "\n")


if __name__ == "__main__":
    main()
