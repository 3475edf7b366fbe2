"""`aefabmap eval`: loop-closure metrics of a bundle on an image sequence with ground truth."""

from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path

from aefabmap.cli.options import add_detector_options, add_workers_option, build_run_config
from aefabmap_runtime.errors import ConfigError
from aefabmap_runtime.core.detector import SCORERS, DetectorConfig
from aefabmap_runtime.core.verify.verification import VerificationConfig


def register(sub) -> None:
    p = sub.add_parser("eval", help="evaluate a bundle on an image sequence (docs/evaluation.md protocol)")
    src = p.add_argument_group("model, sequence and ground truth")
    src.add_argument("--model", required=True, type=Path, metavar="BUNDLE", help="model bundle directory")
    src.add_argument("--images", required=True, type=Path, metavar="DIR", help="frames, sorted by name = temporal order")
    src.add_argument("--gt", required=True, type=Path, metavar="GT.npy", help="bool N x N ground truth")
    src.add_argument("--tolerance", type=int, default=10, help="frames of tolerance for the tolerant metrics (default 10)")
    add_workers_option(src)
    add_detector_options(p, scorers=SCORERS + ("both",))
    out = p.add_argument_group("output")
    out.add_argument("--json", type=Path, metavar="OUT.json",
                     help="write the metrics (and the split of revisits when verifying) as JSON to OUT.json")
    out.add_argument("--frames", type=Path, metavar="OUT.jsonl",
                     help="per-frame evidence, one JSON line per frame (candidates, checks, choice, correctness)")
    out.add_argument("--failures", type=Path, metavar="DIR",
                     help="match images (PNG) of every false positive and every miss whose true place was a candidate")
    out.add_argument("--plot", type=Path, metavar="PR.png", help="PR curves (needs matplotlib)")
    out.add_argument("--score-matrix", type=Path, metavar="M.png", help="score matrix as an image")
    out.add_argument("--state", default=None, metavar="DIR",
                     help="save the map built over the sequence to DIR (for `run --state`/`replay --state`); "
                     "DIR must not hold a map yet: frames of a loaded map are not in the ground truth")
    out.add_argument("--localize", action="store_true",
                     help="with --state DIR holding a map built over the sequence's first frames: localize the "
                     "frames after them against it, read-only, scored on the ground truth cut to the map's frames "
                     "(docs/localization.md); DIR is not written")
    out.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    p.set_defaults(func=run)


def _localize(args, scorers) -> int:
    """`eval --localize`: the frames after the map's, localized against it (tools/localize_eval.py)."""
    from aefabmap_runtime.tools.localize_eval import localize_sequence
    from aefabmap_runtime.tools.reporting import format_table
    from aefabmap_runtime.tools.sequence_eval import public

    if args.state is None:
        raise ConfigError("--localize needs --state DIR: the map to localize against")
    if len(scorers) > 1 or args.frames or args.failures or args.plot or args.score_matrix:
        raise ConfigError("--localize reports the metrics (--json): not --scorer both, --frames, --failures, "
                          "--plot or --score-matrix")
    run_config = build_run_config(args)
    config = dataclasses.replace(run_config.detector, scorer=scorers[0])
    metrics, run = localize_sequence(args.model, args.images, args.gt, args.state, config, args.tolerance,
                                     not args.no_progress, workers=run_config.workers)
    print(f"localized frames {run.first}-{run.first + metrics['queries'] - 1} against the map's "
          f"{run.map_places} places (frames 0-{run.first - 1})")
    print(format_table({f"{scorers[0]} verified (output)": metrics["verified"],
                        f"{scorers[0]} raw": metrics}))
    if args.json:
        args.json.write_text(json.dumps(public({**metrics, "map_places": run.map_places}), indent=2) + "\n")
    return 0


def run(args) -> int:
    from aefabmap_runtime.tools.reporting import (
        format_table,
        require_plotting,
        save_pr_plot,
        save_score_matrix,
    )
    from aefabmap_runtime.tools.sequence_eval import evaluate_bundle, public

    if args.plot:
        require_plotting()  # fail before a long run, not after it
    if args.failures and args.no_verify:
        raise ConfigError("--failures shows verified matches and misses: it needs verification (drop --no-verify)")
    scorers = SCORERS if args.scorer == "both" else (args.scorer or DetectorConfig().scorer,)
    if args.localize:
        return _localize(args, scorers)
    save_state = None
    if args.state is not None:
        if len(scorers) > 1:
            raise ConfigError("--state keeps one map: choose --scorer fabmap or bow, not both")
        from aefabmap_runtime.adapters.node_state import new_map_saver

        save_state = new_map_saver(args.state, logging.getLogger("aefabmap.eval"))
    run_config = build_run_config(args, keep_inlier_points=bool(args.failures))
    verification = run_config.detector.verification
    rows, runs, table = {}, {}, {}
    for scorer in scorers:
        config = dataclasses.replace(run_config.detector, scorer=scorer)
        rows[scorer], runs[scorer] = evaluate_bundle(args.model, args.images, args.gt, config, args.tolerance,
                                                     not args.no_progress, after_run=save_state,
                                                     workers=run_config.workers)
        # The product's output (verified) first, then the raw score it starts from.
        if "verified" in rows[scorer]:
            table[f"{scorer} verified (output)"] = rows[scorer]["verified"]
        raw_score = run_config.detector.fabmap_score if scorer == "fabmap" else "cosine"
        table[f"{scorer} raw ({raw_score})"] = rows[scorer]
    print(format_table(table))
    from aefabmap_runtime.tools.frame_evidence import format_revisit_split, revisit_split

    wanted = verification.enabled or args.frames or args.failures
    records = evidence_records(args, runs[scorers[0]], verification) if wanted else []
    split = revisit_split(records) if verification.enabled else None
    if split is not None:
        print(format_revisit_split(split))
    if args.frames or args.failures:
        write_evidence(args, runs[scorers[0]], records)
    main = rows[scorers[0]]
    if args.json:
        doc = public(main)
        if split is not None:
            doc["revisits"] = split
        doc["methods"] = {k: public(v) for k, v in rows.items()}
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(doc, indent=2) + "\n")
    if args.plot:
        save_pr_plot(table, args.plot)
    if args.score_matrix:
        save_score_matrix(runs[scorers[0]].score_matrix, args.score_matrix)
    return 0


def evidence_records(args, run, verification: VerificationConfig) -> list[dict]:
    """Per-frame evidence records of the first scorer's run (runtime/aefabmap_runtime/tools/frame_evidence.py)."""
    from aefabmap_runtime.tools.frame_evidence import frame_records, min_evidence_keypoints

    return list(frame_records(run.results, run.ground_truth, args.tolerance, min_evidence_keypoints(verification),
                              verification.max_log10_nfa))


def write_evidence(args, run, records: list[dict]) -> None:
    """--frames / --failures of the first scorer's run."""
    from aefabmap_runtime.tools.frame_evidence import failure_cases, write_failure_images, write_frames_jsonl

    if args.frames:
        write_frames_jsonl(args.frames, records)
    if args.failures:
        written = write_failure_images(args.failures, run.images, failure_cases(run.results, records, args.tolerance))
        print(f"{len(written)} failure images in {args.failures}")
