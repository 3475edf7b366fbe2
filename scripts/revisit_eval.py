#!/usr/bin/env python
"""One bundle on the training revisit sequences, by day and at night, summed over the drives.

Each CamVid drive's revisit sequence (scripts/revisit_sequences.py, written under `--sequences`
when missing; with `--reverse` the second pass is driven back) is evaluated with `aefabmap eval
--exclude 15 --tolerance 1 --fabmap-score llr` plus any eval options given after `--`; the revisit
split each run reports (verified, wrong place, misses by reason) is summed over the drives. Prints
one row for the day and one for the night; `--json` writes the sums and every drive's split.
TRAINING data only: settings may be chosen here.

    python scripts/revisit_eval.py --model BUNDLE --data DATA --sequences revisits [--reverse] [--json r.json] \\
        [-- --verify-bruteforce 1]
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import sys
import tempfile
from pathlib import Path

from calibrate_sequence import drives  # the training drives, one list of frames each
from revisit_sequences import filler, write_sequence  # the sequences' one definition

from aefabmap.cli.main import main as aefabmap_main
from aefabmap_runtime.tools.frame_evidence import revisit_split

#: The eval options every drive runs with (docs/results.md, "Candidate policy").
EVAL_OPTIONS = ("--exclude", "15", "--tolerance", "1", "--fabmap-score", "llr", "--no-progress")
LIGHTS = ("day", "night")


def ensure_sequences(data: Path, root: Path, step: int, reverse: bool = False) -> dict[str, dict[str, Path]]:
    """{light: {drive: sequence folder}}, written under root/<light>-step<step>[-reverse] when missing."""
    camvid = data / "train" / "camvid"
    if not camvid.is_dir():
        raise SystemExit(f"no CamVid training drives under {camvid}")
    by_drive = drives(camvid)
    out: dict[str, dict[str, Path]] = {}
    for light in LIGHTS:
        out[light] = {}
        for drive, frames in by_drive.items():
            folder = root / f"{light}-step{step}{'-reverse' if reverse else ''}" / drive
            if not (folder / "gt.npy").is_file():
                between = filler(by_drive, drive, step) if reverse else None
                write_sequence(frames, step, folder, night=light == "night", between=between)
            out[light][drive] = folder
    return out


def drive_split(model: Path, folder: Path, extra: list[str]) -> dict:
    """The revisit split `aefabmap eval` reports for one sequence folder (its JSON "revisits")."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "eval.json"
        argv = ["eval", "--model", str(model), "--images", str(folder / "images"), "--gt", str(folder / "gt.npy"),
                *EVAL_OPTIONS, "--json", str(out), *extra]
        with contextlib.redirect_stdout(io.StringIO()):  # each drive's own table: not needed here
            code = aefabmap_main(argv)
        if code != 0 or not out.is_file():
            raise SystemExit(f"eval failed on {folder} (exit {code})")
        doc = json.loads(out.read_text())
    if "revisits" not in doc:
        raise SystemExit("eval reported no revisit split: verification must be on")
    return doc["revisits"]


def summed(splits: dict[str, dict]) -> dict:
    """The splits of several drives added up (the same keys as one split: `revisit_split`'s)."""
    total = revisit_split([])  # every count and every miss reason at 0
    for split in splits.values():
        for key in total.keys() - {"misses"}:
            total[key] += int(split[key])
        for reason, n in split["misses"].items():
            total["misses"][reason] = total["misses"].get(reason, 0) + int(n)
    return total


def table(sums: dict[str, dict]) -> str:
    """A markdown table: one row per light."""
    reasons = list(next(iter(sums.values()))["misses"])
    head = ["", "revisits", "verified", "wrong place", *[r.replace("_", " ") for r in reasons]]
    rows = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for light, s in sums.items():
        cells = [light, s["revisits"], s["verified"], s["wrong_place"], *[s["misses"][r] for r in reasons]]
        rows.append("| " + " | ".join(str(c) for c in cells) + " |")
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> int:
    repo = Path(__file__).resolve().parents[1]
    argv = list(sys.argv[1:] if argv is None else argv)
    cut = argv.index("--") if "--" in argv else len(argv)
    own, extra = argv[:cut], argv[cut + 1:]
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", type=Path, required=True, help="the bundle to evaluate")
    ap.add_argument("--data", type=Path, default=Path(os.environ.get("AEFABMAP_DATA", repo.parent / "shared" / "data")))
    ap.add_argument("--sequences", type=Path, required=True, help="folder of the revisit sequences (written when missing)")
    ap.add_argument("--step", type=int, default=6, help="first pass plays every STEP-th frame (revisit_sequences.py)")
    ap.add_argument("--reverse", action="store_true", help="the second pass driven back (revisit_sequences.py)")
    ap.add_argument("--json", type=Path, help="also write the sums and every drive's split here")
    args = ap.parse_args(own)
    sequences = ensure_sequences(args.data, args.sequences, args.step, args.reverse)
    per_drive = {light: {drive: drive_split(args.model, folder, extra) for drive, folder in folders.items()}
                 for light, folders in sequences.items()}
    sums = {light: summed(splits) for light, splits in per_drive.items()}
    print(table(sums))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        doc = {"model": str(args.model), "step": args.step, "reverse": args.reverse,
               "eval_options": [*EVAL_OPTIONS, *extra], "sums": sums, "drives": per_drive}
        args.json.write_text(json.dumps(doc, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
