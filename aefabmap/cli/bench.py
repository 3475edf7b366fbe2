"""`aefabmap bench ...`: benchmarks that print figures and save JSON."""

from __future__ import annotations

import json
import logging
from dataclasses import asdict
from pathlib import Path

from aefabmap.cli.options import add_verification_options, default_bundle, require_extra

log = logging.getLogger("aefabmap.bench")

# compiled.KERNEL_CHOICES, written out: importing runtime/aefabmap_runtime/core/kernels/compiled.py imports numba, which
# would slow every command's start.
_KERNEL_CHOICES = ("auto", "native", "numba", "numpy")
_KERNELS_HELP = ("the kernels (FAB-MAP scatter, verification's matching, the int8 search's re-rank): auto (default: "
                 "the ahead-of-time compiled ones when built, else numba's JIT when it can run, else numpy), "
                 "native, numba, or numpy / OpenCV")


_JSON_HELP = "also write the JSON printed to OUT"


def register(sub) -> None:
    p = sub.add_parser("bench", help="benchmarks (print figures, save JSON)")
    bsub = p.add_subparsers(dest="bench", required=True)
    _register_inference(bsub)
    _register_chowliu(bsub)
    _register_pipeline(bsub)
    _register_sequence(bsub)
    _register_quantizer(bsub)
    _register_stream(bsub)
    _register_soak(bsub)


def _add_kernels_option(g) -> None:
    g.add_argument("--kernels", "--scatter", dest="scatter", choices=_KERNEL_CHOICES, default="auto", help=_KERNELS_HELP)


def _add_all_cores_option(g) -> None:
    g.add_argument("--all-cores", action="store_true", help="do not restrict the benchmark to one core")


def _add_model_option(g) -> None:
    g.add_argument("--model", type=Path, default=None, metavar="BUNDLE", help="model bundle (default: the shipped one)")


def _add_output_group(p, help: str = _JSON_HELP):
    """p's "output" group, holding --json OUT; returned for the command's other outputs."""
    out = p.add_argument_group("output")
    out.add_argument("--json", type=Path, metavar="OUT", help=help)
    return out


def _register_inference(bsub) -> None:
    inf = bsub.add_parser("inference", help="FAB-MAP localize() time and bytes per place on synthetic places")
    w = inf.add_argument_group("workload (synthetic places)")
    w.add_argument("--places", type=int, nargs="+", required=True, metavar="N",
                   help="places in the map; several: one map and one timing per value")
    w.add_argument("--words", type=int, default=10_000, metavar="V", help="vocabulary size (default 10000)")
    w.add_argument("--queries", type=int, default=200, metavar="N", help="timed localize() calls per map (default 200)")
    w.add_argument("--words-per-place", type=int, default=300, metavar="K",
                   help="words observed by each synthetic place and query (default 300)")
    _add_kernels_option(inf.add_argument_group("measurement"))
    _add_output_group(inf)
    inf.set_defaults(func=run_inference)


def _register_chowliu(bsub) -> None:
    cl = bsub.add_parser("chowliu", help="Chow-Liu learning time and peak memory on synthetic observations")
    w = cl.add_argument_group("workload (synthetic observations)")
    w.add_argument("--words", type=int, default=10_000, metavar="V", help="vocabulary size (default 10000)")
    w.add_argument("--images", type=int, default=5_000, metavar="N",
                   help="training observations (one per image) the tree is learnt from (default 5000)")
    w.add_argument("--words-per-image", type=int, default=300, metavar="K",
                   help="words observed by each synthetic image (default 300)")
    _add_output_group(cl)
    cl.set_defaults(func=run_chowliu)


def _register_pipeline(bsub) -> None:
    pl = bsub.add_parser("pipeline", help="per-stage ms per 640x480 ORB frame on one core with a pre-filled map")
    m = pl.add_argument_group("map and model")
    _add_model_option(m)
    m.add_argument("--places", type=int, default=10_000, metavar="N", help="places in the map before timing (default 10000)")
    m.add_argument("--prefill", choices=("train", "synthetic"), default="train",
                   help="word sets of the pre-filled places: the bundle's training observations (default) "
                   "or synthetic observations of the same mean size")
    m.add_argument("--words-only-places", action="store_true",
                   help="pre-filled places without keypoints (never verified, so verification is understated; "
                        "the mode of figures measured before this option existed)")
    fr = pl.add_argument_group("frames")
    fr.add_argument("--frames", type=int, default=150, metavar="N", help="timed frames (default 150)")
    fr.add_argument("--warmup", type=int, default=10, metavar="N", help="untimed frames first (default 10)")
    v = pl.add_argument_group("verification")
    v.add_argument("--no-verification", action="store_true", help="switch geometric verification off")
    add_verification_options(v, "--verify-keypoints", "--verify-bruteforce", bench=True)
    me = pl.add_argument_group("measurement")
    _add_kernels_option(me)
    _add_all_cores_option(me)
    _add_output_group(pl)
    pl.set_defaults(func=run_pipeline)


def _register_sequence(bsub) -> None:
    sq = bsub.add_parser("sequence", help="per-stage ms per frame of the runtime's own path over a folder of real "
                         "images, on one core")
    i = sq.add_argument_group("input and detector")
    i.add_argument("--images", type=Path, required=True, metavar="DIR", help="image folder (file-name order)")
    _add_model_option(i)
    i.add_argument("--exclude", type=int, default=50, metavar="N", help="exclusion window, frames (default 50)")
    i.add_argument("--limit", type=int, default=None, metavar="N", help="first N images only")
    add_verification_options(sq.add_argument_group("verification"), "--verify-keypoints", "--verify-bruteforce",
                             "--no-verify-upright", bench=True)
    me = sq.add_argument_group("measurement")
    _add_kernels_option(me)
    _add_all_cores_option(me)
    me.add_argument("--calls", action="store_true", help="then a second pass under the profiler: CPU ms per frame "
                    "inside OpenCV, onnxruntime and aefabmap's compiled kernels (the rest: Python and numpy)")
    me.add_argument("--workers", type=int, default=1, metavar="N",
                    help="then a run with N threads working on frames on N cores: CPU ms per frame, frames per "
                    "second and stages beside the one-thread run's (default 1: that run only)")
    _add_output_group(sq)
    sq.set_defaults(func=run_sequence)


def _register_quantizer(bsub) -> None:
    qz = bsub.add_parser("quantizer", help="ms to quantise 500 real descriptors on one thread (flat, tree, AE fp32/int8)")
    i = qz.add_argument_group("quantiser and descriptors")
    _add_model_option(i)
    i.add_argument("--variant", default=None,
                   choices=("kmeans-flat", "kmeans-flat-fp32", "kmeans-indexed", "kmeans-tree", "ae-fp32", "ae-int8",
                            "fp32", "int8"),
                   help="quantiser to time: the bundle's own (default; k-means with an index: kmeans-indexed; "
                   "AE: ae-fp32), kmeans-flat on an indexed bundle (exhaustive search; binary kinds: int8 product "
                   "with exact re-rank), kmeans-flat-fp32 (the same search as one float32 product), ae-int8 / int8 "
                   "on an AE bundle")
    i.add_argument("--data", type=Path, default=None, metavar="DIR",
                   help="data root whose train/scene15 images give the descriptors (default: $AEFABMAP_DATA; "
                   "without it, synthetic frames)")
    me = qz.add_argument_group("measurement")
    me.add_argument("--repeats", type=int, default=200, metavar="N", help="timed calls (default 200)")
    _add_all_cores_option(me)
    _add_output_group(qz)
    qz.set_defaults(func=run_quantizer)


def _register_stream(bsub) -> None:
    st = bsub.add_parser("stream", help="two processes over loopback Zenoh: frames/s, latency, 200 Hz flood, RSS at the cap")
    src = st.add_argument_group("model and frames")
    _add_model_option(src)
    src.add_argument("--frames", type=int, default=160, metavar="N", help="distinct synthetic frames, cycled (default 160)")
    ph = st.add_argument_group("phases (rates and lengths)")
    ph.add_argument("--rate", type=float, default=30.0, metavar="HZ", help="rate of the latency phase (default 30)")
    ph.add_argument("--seconds", type=float, default=15.0, metavar="S", help="length of the latency phase (default 15)")
    ph.add_argument("--throughput-seconds", type=float, default=15.0, metavar="S",
                    help="length of the closed-loop throughput phase (default 15)")
    ph.add_argument("--window", type=int, default=2, metavar="N",
                    help="frames in flight in the throughput phase (default 2)")
    ph.add_argument("--flood-rate", type=float, default=200.0, metavar="HZ", help="flood rate (default 200)")
    ph.add_argument("--flood-seconds", type=float, default=10.0, metavar="S", help="flood length (default 10)")
    ph.add_argument("--soak-seconds", type=float, default=60.0, metavar="S",
                    help="length of the RSS run at the cap (default 60; 0 skips it)")
    ph.add_argument("--soak-rate", type=float, default=30.0, metavar="HZ", help="rate of the RSS run (default 30)")
    node = st.add_argument_group("the node's options")
    node.add_argument("--max-places", type=int, default=100, metavar="N", help="the node's --max-places (default 100)")
    node.add_argument("--memory-mb", type=float, default=None, metavar="MB", help="the node's --memory-mb")
    node.add_argument("--queue", type=int, default=2, metavar="N", help="the node's --queue (default 2)")
    node.add_argument("--image-every", type=int, default=1, metavar="N", help="the node's --image-every (default 1)")
    node.add_argument("--node-threads", type=int, default=1, metavar="N",
                      help="OMP_NUM_THREADS/OPENBLAS_NUM_THREADS of the node (default 1, as deploy/aefabmap.service; "
                      "0: inherit this environment)")
    out = _add_output_group(st)
    out.add_argument("--workdir", type=Path, default=None, metavar="DIR",
                     help="keep the node's MCAP log and stderr here (default: a temporary directory)")
    st.set_defaults(func=run_stream)


def _register_soak(bsub) -> None:
    so = bsub.add_parser("soak", help="RSS over a long run at the map cap: a real node fed N frames over Zenoh, "
                         "and M observations straight into the detector core")
    both = so.add_argument_group("both phases")
    _add_model_option(both)
    both.add_argument("--max-places", type=int, default=2000, metavar="N", help="map cap of both phases (default 2000)")
    both.add_argument("--flat-mb", type=float, default=5.0, metavar="MB",
                      help="allowed RSS range after warm-up (default 5)")
    both.add_argument("--max-minutes", type=float, default=None, metavar="MIN",
                      help="stop each phase after MIN minutes if not done (reported; default: no limit)")
    pp = so.add_argument_group("pipeline phase (a real node fed over Zenoh)")
    pp.add_argument("--frames", type=int, default=100_000, metavar="N",
                    help="frames through the full pipeline (default 100000; 0 skips that phase)")
    pp.add_argument("--rate", type=float, default=30.0, metavar="HZ",
                    help="publish rate of the pipeline phase (default 30; 0: closed loop, --window frames in flight)")
    pp.add_argument("--window", type=int, default=2, metavar="N", help="frames in flight in closed loop (default 2)")
    pp.add_argument("--size", type=_size, default=(640, 480), metavar="WxH", help="frame size (default 640x480)")
    pp.add_argument("--mcap-max-mb", type=float, default=20.0, metavar="MB", help="the node's --mcap-max-mb (default 20)")
    pp.add_argument("--log-budget-mb", type=float, default=100.0, metavar="MB",
                    help="the node's --log-budget-mb (default 100)")
    pp.add_argument("--image-every", type=int, default=1, metavar="N", help="the node's --image-every (default 1)")
    pp.add_argument("--node-threads", type=int, default=1, metavar="N",
                    help="OMP/OPENBLAS_NUM_THREADS of the node (default 1; 0: inherit this environment)")
    pp.add_argument("--frame-checkpoints", type=int, nargs="+", default=None, metavar="N",
                    help="frame counts where the node's RSS is sampled (default 1000 10000 50000 100000)")
    pp.add_argument("--warmup-frames", type=int, default=10_000, metavar="N",
                    help="RSS from this frame count on must stay within --flat-mb (default 10000)")
    pp.add_argument("--sample-seconds", type=float, default=5.0, metavar="S",
                    help="period of the pipeline phase's RSS samples besides the checkpoints (default 5)")
    core = so.add_argument_group("core phase (observations straight into the detector core)")
    core.add_argument("--observations", type=int, default=1_000_000, metavar="M",
                      help="observations straight into the detector core (default 1000000; 0 skips that phase)")
    core.add_argument("--observation-checkpoints", type=int, nargs="+", default=None, metavar="N",
                      help="observation counts where RSS is sampled (default 1000 10000 100000 500000 1000000)")
    core.add_argument("--warmup-observations", type=int, default=10_000, metavar="N",
                      help="the same as --warmup-frames for the core phase (default 10000)")
    core.add_argument("--core-vocabulary", type=int, default=0, metavar="V",
                      help="core phase on a random Chow-Liu tree over V words instead of the bundle's vocabulary "
                      "(default 0: the bundle's)")
    core.add_argument("--core-words", type=int, default=300, metavar="K",
                      help="words per observation with --core-vocabulary (default 300)")
    out = _add_output_group(so, "write the results as JSON to OUT (the figures are printed)")
    out.add_argument("--workdir", type=Path, default=None, metavar="DIR",
                     help="keep the node's MCAP logs and stderr here (default: a temporary directory)")
    so.set_defaults(func=run_soak)


def _size(text: str) -> tuple[int, int]:
    import argparse

    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must be WxH, e.g. 320x240, got {text!r}") from None
    return w, h


def _emit(doc, path: Path | None) -> None:
    text = json.dumps(doc, indent=2)
    print(text)
    if path:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text + "\n")


def run_inference(args) -> int:
    from aefabmap_runtime.core.kernels import compiled
    from aefabmap_runtime.tools.synthetic_observations import bench_inference

    previous = compiled.use(True if args.scatter == "auto" else args.scatter)
    log.info("kernels: %s", compiled.describe())
    try:
        results = [asdict(bench_inference(n, args.words, queries=args.queries, words_per_place=args.words_per_place))
                   for n in args.places]
    finally:
        compiled.use(previous)
    _emit(results[0] if len(results) == 1 else results, args.json)
    return 0


def run_chowliu(args) -> int:
    require_extra("bench chowliu", "train", ("scipy",))  # the trainer's Chow-Liu learning
    from aefabmap_trainer.benchmark import bench_chow_liu

    _emit(asdict(bench_chow_liu(args.images, args.words, args.words_per_image)), args.json)
    return 0


def _model(args) -> Path:
    return args.model or default_bundle()


def run_pipeline(args) -> int:
    from aefabmap_runtime.tools.stream_bench import PipelineBenchConfig, bench_pipeline

    cfg = PipelineBenchConfig(
        bundle=str(_model(args)), places=args.places, frames=args.frames, warmup=args.warmup,
        prefill=args.prefill, verification=not args.no_verification, single_core=not args.all_cores,
        verify_keypoints=args.verify_keypoints, verify_bruteforce=args.verify_bruteforce,
        place_keypoints=not args.words_only_places, scatter=args.scatter,
    )
    doc = bench_pipeline(cfg)
    _emit(doc, args.json)
    s = doc["stages_ms"]
    print(f"\n{doc['bundle']}: {doc['vocabulary_size']} words, {doc['places_in_map']['max']} places, "
          f"{'one core' if doc['single_core'] else 'all cores'}, load {doc['machine']['load_average']}")
    c = doc["stages_cpu_ms"]
    print(f"{'stage':<24}{'wall median':>12}{'wall p95':>10}{'CPU median':>12}{'CPU p95':>10}  (ms)")
    for name in ("decode", "features", "quantise", "inference", "verification"):
        print(f"{name:<24}{s[name]['median']:>12.2f}{s[name]['p95']:>10.2f}{c[name]['median']:>12.2f}{c[name]['p95']:>10.2f}")
    w, u = doc["total_ms"], doc["total_cpu_ms"]
    print(f"{'total':<24}{w['median']:>12.2f}{w['p95']:>10.2f}{u['median']:>12.2f}{u['p95']:>10.2f}")
    v = doc["total_without_verification_ms"]
    print(f"{'total w/o verification':<24}{v['median']:>12.2f}{v['p95']:>10.2f}")
    t = doc["target"]
    print(f"target median <= 10 ms: wall {'MET' if t['met_wall'] else 'MISSED'}, CPU {'MET' if t['met_cpu'] else 'MISSED'}")
    return 0


def run_sequence(args) -> int:
    from aefabmap_runtime.tools.sequence_bench import STAGES, SequenceBenchConfig, bench_sequence

    doc = bench_sequence(SequenceBenchConfig(images=str(args.images), bundle=str(_model(args)), exclude=args.exclude,
                                             limit=args.limit, scatter=args.scatter, single_core=not args.all_cores,
                                             calls=args.calls, verify_keypoints=args.verify_keypoints,
                                             verify_bruteforce=args.verify_bruteforce,
                                             verify_upright=args.verify_upright, workers=args.workers))
    _emit(doc, args.json)
    s, c = doc["stages_ms"], doc["stages_cpu_ms"]
    print(f"\n{doc['images']}: {doc['frames']} frames of {doc['image_size_wh']}, {doc['loops']} loops, "
          f"{doc['places_verified_per_frame']['mean']} places verified per frame (keypoints "
          f"{doc['verify_keypoints']}, retries {doc['verify_bruteforce']}, upright {doc['verify_upright']}), "
          f"kernels {doc['scatter']}, "
          f"{'one core' if doc['single_core'] else 'all cores'}, load {doc['machine']['load_average']}")
    print(f"{'stage':<16}{'wall median':>12}{'wall p95':>10}{'CPU median':>12}{'CPU mean':>10}  (ms)")
    for name in STAGES:
        print(f"{name:<16}{s[name]['median']:>12.2f}{s[name]['p95']:>10.2f}{c[name]['median']:>12.2f}"
              f"{c[name]['mean']:>10.2f}")
    w, u = doc["total_ms"], doc["total_cpu_ms"]
    print(f"{'total':<16}{w['median']:>12.2f}{w['p95']:>10.2f}{u['median']:>12.2f}{u['mean']:>10.2f}")
    print(f"{doc['frames_per_second']} frames per second")
    if "calls_cpu_ms_per_frame" in doc:
        print("CPU ms per frame (mean) inside: " + ", ".join(f"{k} {v:.2f}" for k, v in doc["calls_cpu_ms_per_frame"].items()))
    if len(doc["workers"]) > 1:
        print(f"\n{'workers':<8}{'CPU ms/frame':>13}{'frames/s':>10}{'wall s':>8}  mean wall ms per frame: "
              + " ".join(STAGES))
        for n, w in doc["workers"].items():
            print(f"{n:<8}{w['cpu_ms_per_frame']:>13.2f}{w['frames_per_second']:>10.2f}{w['wall_s']:>8.1f}  "
                  + " ".join(f"{w['stages_ms_mean'][k]:.2f}" for k in STAGES))
    return 0


def run_quantizer(args) -> int:
    import os

    from aefabmap_runtime.tools.quantizer_bench import QuantizerBenchConfig, bench_quantizer

    data = args.data or os.environ.get("AEFABMAP_DATA")
    cfg = QuantizerBenchConfig(bundle=str(_model(args)), variant=args.variant, repeats=args.repeats,
                               data=str(data) if data else None, single_core=not args.all_cores)
    doc = bench_quantizer(cfg)
    _emit(doc, args.json)
    print(f"\n{doc['variant']} ({doc['feature_kind']}, {doc['words']} words): {doc['ms_per_500_median']} ms per 500 "
          f"descriptors (median; p95 {doc['ms_per_500_p95']}; CPU median {doc['cpu_ms_per_500_median']}), "
          f"load {doc['machine']['load_average']}")
    return 0


def run_stream(args) -> int:
    from aefabmap_runtime.tools.stream_bench import StreamBenchConfig, bench_stream

    cfg = StreamBenchConfig(
        bundle=str(_model(args)), rate_hz=args.rate, seconds=args.seconds,
        throughput_seconds=args.throughput_seconds, window=args.window, flood_hz=args.flood_rate,
        flood_seconds=args.flood_seconds, soak_seconds=args.soak_seconds, soak_rate_hz=args.soak_rate,
        max_places=args.max_places, memory_mb=args.memory_mb, queue=args.queue, image_every=args.image_every,
        n_frames=args.frames, workdir=str(args.workdir) if args.workdir else None,
        keep_log=args.workdir is not None, node_threads=args.node_threads or None,
    )
    doc = bench_stream(cfg)
    _emit(doc, args.json)
    print()
    for name, ph in doc["phases"].items():
        lat = ph["latency_ms"]
        fps = ph.get("fps", ph.get("processed_fps"))
        print(f"{name:<11} {ph['mode']:<30} published {ph['published']:>5}  processed {ph['processed']:>5}  "
              f"{fps} fps  latency p50 {lat['median']} ms p95 {lat['p95']} ms max {lat['max']} ms")
    r = doc["rss_mb"]
    print(f"node RSS MB: first {r['first']}, last {r['last']}, max {r['max']} ({r['samples']} samples)")
    for name, t in doc["targets"].items():
        print(f"target {name}: {'MET' if t['met'] else 'MISSED'} {t}")
    return 0


def run_soak(args) -> int:
    from aefabmap_runtime.tools.soak_bench import (
        FRAME_CHECKPOINTS,
        OBSERVATION_CHECKPOINTS,
        SoakConfig,
        bench_soak,
    )

    cfg = SoakConfig(
        bundle=str(_model(args)), frames=args.frames, observations=args.observations, max_places=args.max_places,
        rate_hz=args.rate, window=args.window, size=args.size, mcap_max_mb=args.mcap_max_mb,
        log_budget_mb=args.log_budget_mb, image_every=args.image_every,
        frame_checkpoints=tuple(args.frame_checkpoints or FRAME_CHECKPOINTS),
        observation_checkpoints=tuple(args.observation_checkpoints or OBSERVATION_CHECKPOINTS),
        warmup_frames=args.warmup_frames, warmup_observations=args.warmup_observations, flat_mb=args.flat_mb,
        sample_period_s=args.sample_seconds, core_vocabulary=args.core_vocabulary, core_words=args.core_words,
        max_seconds=args.max_minutes * 60 if args.max_minutes else None, node_threads=args.node_threads or None,
        workdir=str(args.workdir) if args.workdir else None,
    )
    doc = bench_soak(cfg)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(doc, indent=2) + "\n")
    print(f"load average at the end: {doc['machine']['load_average']}")
    for name, count in (("pipeline", "frames"), ("core", "observations")):
        ph = doc[name]
        if ph is None:
            continue
        print(f"\n{name}: RSS MB at {count}")
        for s in ph["checkpoints"]:
            print(f"  {s[count]:>9}  {s['rss_mb']:>8}  places {s['places']}"
                  + (f"  log files {s['log_files']} bytes {s['log_bytes']}" if name == "pipeline" else ""))
        for label, f in (("warm-up", ph["rss_flat"]), ("map full", ph["rss_flat_at_cap"])):
            verdict = {True: "FLAT", False: "NOT FLAT", None: "too short to judge"}[f["met"]]
            print(f"  {label}, from {f['warmup']} {count}: range {f['range_mb']} MB, growth {f['growth_mb']} MB over "
                  f"{f['samples']} samples -> {verdict} (within {f['flat_mb']} MB)")
        if ph["stopped_at_max_seconds"]:
            print("  stopped at --max-minutes")
        if name == "pipeline":
            lg = ph["log"]
            print(f"  published {ph['frames_published']}, processed {ph['frames_processed']} "
                  f"({ph['processed_fps']} fps), not processed {ph['not_processed']}; log files created "
                  f"{lg['files_created']}, deleted {lg['files_deleted']}, on disk at the end {lg['dir_end']['files']} "
                  f"({lg['dir_end']['bytes']} bytes), errors {lg['errors']}")
    return 0
