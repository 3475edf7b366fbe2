"""`aefabmap bench ...`: benchmarks that print figures and save JSON."""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path


def register(sub) -> None:
    p = sub.add_parser("bench", help="benchmarks (print figures, save JSON)")
    bsub = p.add_subparsers(dest="bench", required=True)
    inf = bsub.add_parser("inference", help="FAB-MAP localize() time and bytes per place on synthetic places")
    inf.add_argument("--places", type=int, nargs="+", required=True, metavar="N")
    inf.add_argument("--words", type=int, default=10_000, metavar="V")
    inf.add_argument("--queries", type=int, default=200)
    inf.add_argument("--words-per-place", type=int, default=300)
    inf.add_argument("--json", type=Path, metavar="OUT")
    inf.set_defaults(func=run_inference)
    cl = bsub.add_parser("chowliu", help="Chow-Liu learning time and peak memory on synthetic observations")
    cl.add_argument("--words", type=int, default=10_000, metavar="V")
    cl.add_argument("--images", type=int, default=5_000, metavar="N")
    cl.add_argument("--words-per-image", type=int, default=300)
    cl.add_argument("--json", type=Path, metavar="OUT")
    cl.set_defaults(func=run_chowliu)


def _emit(doc, path: Path | None) -> None:
    text = json.dumps(doc, indent=2)
    print(text)
    if path:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text + "\n")


def run_inference(args) -> int:
    from aefabmap.runtime.benchmark import bench_inference

    results = [asdict(bench_inference(n, args.words, queries=args.queries, words_per_place=args.words_per_place)) for n in args.places]
    _emit(results[0] if len(results) == 1 else results, args.json)
    return 0


def run_chowliu(args) -> int:
    from aefabmap.trainer.benchmark import bench_chow_liu

    _emit(asdict(bench_chow_liu(args.images, args.words, args.words_per_image)), args.json)
    return 0
