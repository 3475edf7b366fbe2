"""The options several commands share, each declared once, and their reading into typed settings.

The one place that turns command-line options into a RunConfig (runtime/aefabmap_runtime/core/run_config.py):
`run` and `eval` share the detector options below; `replay` reads the run's RunConfig from its log
instead. Precedence: an explicit option, then the `--profile` preset, then the defaults in code.
Commands import this module and no other command's.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.util

from aefabmap import default_bundle  # re-exported: the commands' default --model
from aefabmap_runtime.core.decide.candidates import CandidateConfig
from aefabmap_runtime.core.detector import FABMAP_SCORES, SCORERS, DetectorConfig
from aefabmap_runtime.core.fleet.fleet_map import FleetConfig
from aefabmap_runtime.core.profiles import PROFILES, get_profile
from aefabmap_runtime.core.run_config import RunConfig
from aefabmap_runtime.core.verify.verification import VerificationConfig
from aefabmap_runtime.errors import ConfigError

VARIANTS = ("fp32", "int8", "flat", "flat-fp32")

#: The exit codes every command shares (runtime/aefabmap_runtime/errors.py), for the end of each --help.
EXIT_CODES = ("exit codes: 0 success; 1 failure (replay --check: results differ); 2 bad option or "
              "configuration; 3 bad model bundle or map state; 4 bad input data; 5 transport (Zenoh) error; "
              "6 log (MCAP) error; 130 interrupted")


#: Import names of the `train` extra's packages (pyproject.toml) that the trainer imports: torch
#: (autoencoder), scipy (Chow-Liu tree), onnx and onnxscript (the ONNX export, at the end of training).
TRAIN_EXTRA_MODULES = ("torch", "scipy", "onnx", "onnxscript")


def require_extra(command: str, extra: str, modules: tuple[str, ...]) -> None:
    """Raise ConfigError naming `pip install 'aefabmap[extra]'` unless `modules` are installed.

    Checked before any work starts (a missing onnx would otherwise surface only at the export,
    after training); the modules are found, not imported (torch takes seconds to import).
    """
    missing = []
    for name in modules:
        try:
            found = importlib.util.find_spec(name) is not None
        except (ImportError, ValueError):
            found = False
        if not found:
            missing.append(name)
    if missing:
        raise ConfigError(f"aefabmap {command} needs {', '.join(missing)}, which this install lacks: "
                          f"pip install 'aefabmap[{extra}]'")


def add_zenoh_options(p: argparse.ArgumentParser, group=None, *, config: bool = True) -> None:
    """--connect / --listen (repeatable or comma-separated) and --config (zenoh JSON5 file), in
    `group` (an argument group of p) when given; the network note goes to p's epilog."""
    g = group if group is not None else p
    g.add_argument("--connect", action="append", metavar="EP", default=[],
                   help="zenoh endpoint to connect to, e.g. tcp/192.168.1.10:7447 (repeatable)")
    g.add_argument("--listen", action="append", metavar="EP", default=[],
                   help="zenoh endpoint to listen on, e.g. tcp/192.168.1.20:7447 (repeatable; a non-loopback "
                   "endpoint without mutual TLS needs --allow-exposure)")
    g.add_argument("--allow-exposure", action="store_true",
                   help="accept a session other hosts reach without authentication (a non-loopback listen "
                   "endpoint without mutual TLS, or multicast scouting), from --listen or --config, and a "
                   "non-loopback --foxglove-host; logged at start")
    if config:
        g.add_argument("--config", metavar="zenoh.json5", default=None,
                       help="zenoh JSON5 configuration file (--connect/--listen override it)")
    p.epilog = ("Network: with none of --connect/--listen/--config, `run` listens on tcp/127.0.0.1:7447 only and "
                "`publish` connects there; no multicast scouting.")


def endpoints(args: argparse.Namespace):
    """The node_session.Endpoints of the options `add_zenoh_options` added."""
    from aefabmap_runtime.adapters.node_session import Endpoints

    return Endpoints(connect=tuple(args.connect), listen=tuple(args.listen), config_file=getattr(args, "config", None),
                     allow_exposure=args.allow_exposure)


def add_log_rotation_options(p: argparse.ArgumentParser) -> None:
    """--mcap-max-mb, --log-budget-mb and the free-space thresholds (rotating_log.LogRotationConfig)."""
    p.add_argument("--mcap-max-mb", type=float, default=None, metavar="MB",
                   help="start a new log file before the current one passes MB (default: one file)")
    p.add_argument("--log-budget-mb", type=float, default=None, metavar="MB",
                   help="delete the oldest closed files of the log set to keep it within MB (default: no limit)")
    p.add_argument("--log-min-free-mb", type=float, nargs=2, default=None, metavar=("IMAGES", "RESULTS"),
                   help="stop logging images below IMAGES MB free on the log's disk, everything below RESULTS "
                   "(default: max(500, 2 x --mcap-max-mb) and 100)")


def log_rotation_config(args: argparse.Namespace):
    """The LogRotationConfig of the parsed options (ConfigError when inconsistent)."""
    from aefabmap_runtime.adapters.rotating_log import LogRotationConfig

    min_free = args.log_min_free_mb
    free = {} if min_free is None else {"images_min_free_mb": min_free[0], "results_min_free_mb": min_free[1]}
    return LogRotationConfig(max_mb=args.mcap_max_mb, budget_mb=args.log_budget_mb, **free)


def add_mcap_profile_option(p: argparse.ArgumentParser) -> None:
    """--mcap-profile: the layout of the written log (mcap_log.McapLogConfig.profile)."""
    p.add_argument("--mcap-profile", choices=("aefabmap", "ros2"), default="aefabmap",
                   help="layout of the MCAP log: aefabmap (default: protobuf image, JSON results) or ros2 (CDR "
                   "sensor_msgs/CompressedImage on /camera/image/compressed, std_msgs/String JSON results and stats; "
                   "ros2 bag play, rosbags and Foxglove read it, replay too)")


def add_foxglove_options(p: argparse.ArgumentParser) -> None:
    """--foxglove [PORT] and --foxglove-host: the live view (runtime/aefabmap_runtime/adapters/foxglove_view.py)."""
    p.add_argument("--foxglove", type=int, nargs="?", const=8765, default=None, metavar="PORT",
                   help="serve a live view over the Foxglove WebSocket protocol on PORT (default 8765; 0: any free "
                   "port) to viewers offering foxglove.sdk.v1 (current Foxglove, Lichtblick) or only "
                   "foxglove.websocket.v1 (Lichtblick up to 1.21, older Foxglove Studio): camera image, inlier "
                   "matches, matched place, result and stats plots (layout: deploy/foxglove_layout.json; needs "
                   "aefabmap[foxglove])")
    p.add_argument("--foxglove-host", default="127.0.0.1", metavar="HOST",
                   help="address the Foxglove server binds (default 127.0.0.1: this machine only; the protocol "
                   "has no authentication, so a non-loopback HOST needs --allow-exposure)")


def add_fleet_options(p: argparse.ArgumentParser):
    """--fleet, --robot and --fleet-timeout-ms (`fleet_config` reads them); returns their group."""
    fl = p.add_argument_group("fleet (robots that recognise each other's places)")
    fl.add_argument("--fleet", default=None, metavar="NAME",
                    help="join this fleet: offer this map's places to the other robots of the same bundle and "
                    "verify loops to theirs (a token: letters, digits, '_', '-')")
    fl.add_argument("--robot", default=None, metavar="ID", help="this robot's id in the fleet (same rules; with "
                    "deploy/zenoh-fleet-robot.json5, its certificate's common name)")
    fl.add_argument("--fleet-timeout-ms", type=int, default=None, metavar="MS",
                    help="how long a frame may wait for other robots' keypoints, all robots together (default 300)")
    return fl


def fleet_config(args: argparse.Namespace) -> FleetConfig | None:
    """The FleetConfig of --fleet / --robot / --fleet-timeout-ms (None: not in a fleet)."""
    opts = vars(args)
    if opts.get("fleet") is None and opts.get("robot") is None:
        return None
    if opts.get("fleet") is None or opts.get("robot") is None:
        raise ConfigError("--fleet and --robot go together")
    timeout = opts.get("fleet_timeout_ms")
    return FleetConfig(name=opts["fleet"], robot=opts["robot"],
                       fetch_timeout_ms=FleetConfig.fetch_timeout_ms if timeout is None else timeout)


def add_state_options(p: argparse.ArgumentParser, *, snapshots: bool = False) -> None:
    """--state DIR: where the map is kept between runs (runtime/aefabmap_runtime/adapters/state_dir.py),
    and, for the live node, --snapshot-every."""
    p.add_argument("--state", default=None, metavar="DIR",
                   help="keep the map in DIR: loaded at start when present, saved at the end"
                   + (" and every --snapshot-every" if snapshots else ""))
    p.add_argument("--localize", action="store_true",
                   help="with --state DIR: localize against DIR's map, read-only: frames are ranked and verified "
                   "against it as usual, but none is inserted, nothing is evicted or written (DIR stays byte for byte as it "
                   "was); memory stays flat (docs/localization.md)")
    if snapshots:
        p.add_argument("--snapshot-every", default="60s", metavar="N{s,m,p}",
                       help="with --state: snapshot every N seconds (60s), minutes (5m) or new places (100p); "
                       "default 60s. Frames between snapshots go to a journal in DIR: a kill -9 or a full disk loses only "
                       "the frames that could not be written")


def add_detector_options(p: argparse.ArgumentParser, *, scorers: tuple[str, ...] = SCORERS,
                         profile: bool = False) -> None:
    """The detector's options, in their own --help groups (defaults: DetectorConfig's, or the profile's)."""
    d = DetectorConfig()
    g = p.add_argument_group("detector")
    if profile:
        g.add_argument("--profile", default=None, choices=tuple(PROFILES), metavar="NAME",
                       help="named preset (runtime/aefabmap_runtime/core/profiles.py): 'board' = ORB 500 keypoints, 3000-word flat "
                       "k-means vocabulary, 1 thread, --memory-mb 64, --queue 2; explicit options win; the bundle "
                       "must be the profile's model")
    g.add_argument("--exclude", type=int, default=None, metavar="N",
                   help=f"exclusion window / insertion delay in frames (default {d.exclude})")
    g.add_argument("--scorer", choices=scorers, default=None,
                   help=f"{' / '.join(scorers)}: FAB-MAP 2.0 or bow (tf-idf cosine) (default {d.scorer})")
    g.add_argument("--variant", choices=VARIANTS, default=None,
                   help="quantiser variant: fp32 / int8 (autoencoder bundles); flat: exhaustive search of a k-means "
                   "bundle that has an inverted index; flat-fp32: that search as one float32 product "
                   f"(default {d.quantizer_variant}, or the profile's)")
    g.add_argument("--threads", type=int, default=None, help=f"onnxruntime threads (default {d.threads})")
    g.add_argument("--motion-model", action="store_true", default=None, help="FAB-MAP motion prior")
    g.add_argument("--naive-bayes", action="store_true", default=None, help="FAB-MAP without the Chow-Liu tree")
    g.add_argument("--fabmap-score", choices=FABMAP_SCORES, default=None,
                   help=f"raw FAB-MAP score: posterior probability or llr (default {d.fabmap_score})")
    g.add_argument("--sequence-frames", type=int, default=None, metavar="N",
                   help="evidence over consecutive frames: N query frames whose checked places line up with "
                   f"stored frames may pass together when no single pair does (default {d.sequence.frames}; 0 = off)")
    g.add_argument("--sequence-margin", type=float, default=None, metavar="LOG10",
                   help="a chain is withheld unless it sums at least LOG10 below every chain ending at a stored frame "
                   f"that is not a neighbour of its own (default {d.sequence.margin_log10_nfa:.3f}: twice as unlikely "
                   "by chance; 0 = no such check, as maps journalled before it ran)")
    g.add_argument("--pair-margin", type=float, default=None, metavar="LOG10",
                   help="a passing pair is withheld unless its log10 NFA lies at least LOG10 below that of every other "
                   "place checked whose stored frame is not a neighbour of its own (default "
                   f"{d.candidates.margin_log10_nfa:.3f}: twice as unlikely by chance; 0 = no such check, as maps "
                   "journalled before it ran)")
    g.add_argument("--temporal-frames", type=int, default=None, metavar="N",
                   help=f"temporal consistency: N preceding frames must agree (default {d.temporal_frames} = off)")
    g.add_argument("--temporal-tolerance", type=int, default=None, metavar="F",
                   help=f"frames by which agreeing matches may differ (default {d.temporal_tolerance})")
    m = p.add_argument_group("map caps")
    m.add_argument("--max-places", type=int, default=None, metavar="N", help="cap on places in the map")
    m.add_argument("--memory-mb", type=float, default=None, metavar="MB",
                   help="memory budget of the map (MB; default: none, or the profile's)")
    add_verification_options(p.add_argument_group("verification"))


def add_workers_option(p: argparse.ArgumentParser) -> None:
    """--workers: threads that work on frames (RunConfig.workers)."""
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help=f"threads that work on frames: the next frames are read, decoded and extracted while one "
                   f"is decided; the results are the same (default {RunConfig().workers}; 2 on a second core)")


def add_verification_options(g, *flags: str, bench: bool = False) -> None:
    """The verification options named by `flags` (default: all of them, in that order) in g, a parser
    or argument group. bench: the benchmarks' shorter help (they run the runtime's defaults)."""
    c, v = CandidateConfig(), VerificationConfig()
    runtime = "(default: the runtime's)"
    declared = {
        "--no-verify": dict(action="store_true", default=None, help="raw FAB-MAP/BoW only: no geometric verification"),
        "--verify-top-k": dict(type=int, default=None, metavar="K",
                               help=f"FAB-MAP candidates verified per frame (default {c.top_k})"),
        "--verify-bruteforce": dict(type=int, default=None, metavar="K", help=(
            f"FAB-MAP candidates checked by all-pairs matching {runtime}" if bench
            else "the best K FAB-MAP candidates are checked by all-pairs matching, the others by same-word "
            f"matching only (default {c.bruteforce_fallback}, every candidate of the default top {c.top_k}; fewer "
            "cost less on frames that are not loops and find fewer loops)")),
        "--verify-track-memory": dict(type=int, default=None, metavar="N",
                                      help="frames after a verified match during which its successors are checked "
                                      f"first (default {c.track_memory}; a map journal written with another value "
                                      "replays with it)"),
        "--verify-track-forwards": dict(dest="verify_track_direction", action="store_false", default=None,
                                        help="the track expects every revisit to run forwards through the "
                                        "stored frames, as maps journalled before it ran (default: it learns the "
                                        "direction, so a route driven back is followed too)"),
        "--verify-keypoints": dict(type=int, default=None, metavar="N", help=(
            "keypoints per frame extracted and matched for verification "
            + (runtime if bench else f"(default {v.keypoints}; FAB-MAP observes the bundle's budget)"))),
        "--no-verify-upright": dict(dest="verify_upright", action="store_false", default=None, help=(
            "no upright descriptors (as run's option)" if bench
            else "no upright descriptors: the brute-force retry matches the oriented ones only (less time and "
            "memory per place; fewer loops where a robot passes a place aside)")),
        "--camera": dict(default=None, metavar="FX,FY,CX,CY",
                         help="pinhole intrinsics in pixels of the images: verify with an essential matrix "
                         "(cheirality-checked) instead of a fundamental matrix"),
    }
    for flag in flags or tuple(declared):
        g.add_argument(flag, **declared[flag])


def build_run_config(args: argparse.Namespace, *, keep_inlier_points: bool = False) -> RunConfig:
    """The RunConfig of options added by `add_detector_options` (plus `--model`, and `--queue` where
    the command has it). keep_inlier_points: the live view or failure images draw the inliers."""
    opts = vars(args)
    prof = get_profile(opts["profile"]) if opts.get("profile") is not None else None
    d, c, v = DetectorConfig(), CandidateConfig(), VerificationConfig()

    def pick(name, default, from_profile=None):
        value = opts.get(name)
        if value is not None:
            return value
        return from_profile if from_profile is not None else default

    verification = VerificationConfig(
        enabled=not opts.get("no_verify"),
        keypoints=pick("verify_keypoints", v.keypoints),
        upright=bool(pick("verify_upright", v.upright)),
        camera=opts.get("camera"),
        keep_inlier_points=keep_inlier_points,
    )
    candidates = CandidateConfig(top_k=pick("verify_top_k", c.top_k),
                                 bruteforce_fallback=pick("verify_bruteforce", c.bruteforce_fallback),
                                 track_memory=pick("verify_track_memory", c.track_memory),
                                 margin_log10_nfa=pick("pair_margin", c.margin_log10_nfa),
                                 track_direction=bool(pick("verify_track_direction", c.track_direction)))
    scorer = pick("scorer", d.scorer)
    detector = DetectorConfig(
        scorer=scorer if scorer in SCORERS else d.scorer,  # eval's "both" picks per run
        exclude=pick("exclude", d.exclude),
        quantizer_variant=pick("variant", d.quantizer_variant, prof.quantizer_variant if prof else None),
        threads=pick("threads", d.threads, prof.threads if prof else None),
        motion_model=bool(pick("motion_model", d.motion_model)),
        naive_bayes=bool(pick("naive_bayes", d.naive_bayes)),
        fabmap_score=pick("fabmap_score", d.fabmap_score),
        max_places=opts.get("max_places"),
        memory_mb=pick("memory_mb", d.memory_mb, prof.memory_mb if prof else None),
        verification=verification,
        candidates=candidates,
        sequence=dataclasses.replace(d.sequence, frames=pick("sequence_frames", d.sequence.frames),
                                     margin_log10_nfa=pick("sequence_margin", d.sequence.margin_log10_nfa)),
        temporal_frames=pick("temporal_frames", d.temporal_frames) if verification.enabled else 0,
        temporal_tolerance=pick("temporal_tolerance", d.temporal_tolerance),
    )
    fleet = fleet_config(args)
    return RunConfig(model=str(opts.get("model", "")), detector=detector, profile=opts.get("profile"),
                     queue=pick("queue", RunConfig().queue, prof.queue if prof else None), fleet=fleet,
                     workers=pick("workers", RunConfig().workers), localize=bool(opts.get("localize")))
