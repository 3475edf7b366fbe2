"""The one place that turns command-line options into a RunConfig (runtime/aefabmap_runtime/core/run_config.py).

`run` and `eval` share the detector options below; `replay` reads the run's RunConfig from
its log instead. Precedence: an explicit option, then the `--profile` preset, then the
defaults in code.
"""

from __future__ import annotations

import argparse
import dataclasses

from aefabmap_runtime.core.decide.candidates import CandidateConfig
from aefabmap_runtime.core.detector import FABMAP_SCORES, SCORERS, DetectorConfig
from aefabmap_runtime.core.fleet.fleet_map import FleetConfig
from aefabmap_runtime.core.profiles import PROFILES, get_profile
from aefabmap_runtime.errors import ConfigError
from aefabmap_runtime.core.run_config import RUN_CONFIG_FORMAT, RunConfig, settings_before_upright
from aefabmap_runtime.core.verify.verification import VerificationConfig

VARIANTS = ("fp32", "int8", "flat", "flat-fp32")

#: Key of the RunConfig inside a log's run metadata (aefabmap.run_config), beside the transport's settings.
RUN_CONFIG_KEY = "run"

#: The exit codes every command shares (runtime/aefabmap_runtime/errors.py), for the end of each --help.
EXIT_CODES = ("exit codes: 0 success; 1 failure (replay --check: results differ); 2 bad option or "
              "configuration; 3 bad model bundle or map state; 4 bad input data; 5 transport (Zenoh) error; "
              "6 log (MCAP) error; 130 interrupted")


def add_detector_options(p: argparse.ArgumentParser, *, scorers: tuple[str, ...] = SCORERS,
                         profile: bool = False) -> None:
    """The detector's options, in their own --help groups (defaults: DetectorConfig's, or the profile's)."""
    d, c, v = DetectorConfig(), CandidateConfig(), VerificationConfig()
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
    g.add_argument("--temporal-frames", type=int, default=None, metavar="N",
                   help=f"temporal consistency: N preceding frames must agree (default {d.temporal_frames} = off)")
    g.add_argument("--temporal-tolerance", type=int, default=None, metavar="F",
                   help=f"frames by which agreeing matches may differ (default {d.temporal_tolerance})")
    m = p.add_argument_group("map caps")
    m.add_argument("--max-places", type=int, default=None, metavar="N", help="cap on places in the map")
    m.add_argument("--memory-mb", type=float, default=None, metavar="MB",
                   help="memory budget of the map (MB; default: none, or the profile's)")
    vg = p.add_argument_group("verification")
    vg.add_argument("--no-verify", action="store_true", default=None,
                    help="raw FAB-MAP/BoW only: no geometric verification")
    vg.add_argument("--verify-top-k", type=int, default=None, metavar="K",
                    help=f"FAB-MAP candidates verified per frame (default {c.top_k})")
    vg.add_argument("--verify-bruteforce", type=int, default=None, metavar="K",
                    help="the best K FAB-MAP candidates are retried with all-pairs matching when same-word "
                    f"matching fails (default {c.bruteforce_fallback}, every candidate of the default top "
                    f"{c.top_k}; fewer cost less on frames that are not loops and find fewer loops)")
    vg.add_argument("--verify-track-memory", type=int, default=None, metavar="N",
                    help="frames after a verified match during which its successors are checked first "
                    f"(default {c.track_memory}; a map journal written with another value replays with it)")
    vg.add_argument("--verify-keypoints", type=int, default=None, metavar="N",
                    help=f"keypoints per frame extracted and matched for verification (default {v.keypoints}; "
                    "FAB-MAP observes the bundle's budget)")
    vg.add_argument("--no-verify-upright", dest="verify_upright", action="store_false", default=None,
                    help="no upright descriptors: the brute-force retry matches the oriented ones only "
                    "(less time and memory per place; fewer loops where a robot passes a place aside)")
    vg.add_argument("--camera", default=None, metavar="FX,FY,CX,CY",
                    help="pinhole intrinsics in pixels of the images: verify with an essential matrix "
                    "(cheirality-checked) instead of a fundamental matrix")


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
                                 track_memory=pick("verify_track_memory", c.track_memory))
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
        sequence=dataclasses.replace(d.sequence, frames=pick("sequence_frames", d.sequence.frames)),
        temporal_frames=pick("temporal_frames", d.temporal_frames) if verification.enabled else 0,
        temporal_tolerance=pick("temporal_tolerance", d.temporal_tolerance),
    )
    fleet = fleet_config(args)
    return RunConfig(model=str(opts.get("model", "")), detector=detector, profile=opts.get("profile"),
                     queue=pick("queue", RunConfig().queue, prof.queue if prof else None), fleet=fleet)


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


def apply_process_settings(config: RunConfig) -> None:
    """Process-wide settings a run implies: OpenCV's thread count under a profile."""
    if config.profile is not None:
        import cv2

        cv2.setNumThreads(config.detector.threads)


def logged_run_config(logged: dict) -> RunConfig:
    """The RunConfig a run wrote into its log's run metadata (`logged`: that record). Logs written
    before the whole configuration was kept carry only the map caps and the camera (they ran as
    _BEFORE_WHOLE_CONFIG says); ConfigError when the record is malformed."""
    if not isinstance(logged, dict):
        raise ConfigError("the log's run configuration is not an object")
    if RUN_CONFIG_KEY in logged:
        doc = logged[RUN_CONFIG_KEY]
        detector = doc.get("detector") if isinstance(doc, dict) else None
        if isinstance(detector, dict) and "sequence" not in detector:
            detector = {**detector, **_BEFORE_CHAINS}
        if isinstance(detector, dict):
            doc = {**doc, "detector": settings_before_upright(detector)}
        return RunConfig.from_dict(doc)
    legacy = {k: logged.get(k) for k in ("max_places", "memory_mb")}
    camera = logged.get("camera")
    detector = {**legacy, "verification": {"camera": camera}, **_BEFORE_WHOLE_CONFIG}
    doc = {"format": RUN_CONFIG_FORMAT, "model": str(logged.get("model", ""))[:4096],
           "detector": settings_before_upright(detector)}
    return RunConfig.from_dict(doc)


#: Logs written before evidence over consecutive frames existed ran without it.
_BEFORE_CHAINS = {"sequence": {"frames": 0}}
#: Logs written before the whole configuration was kept also retried only FAB-MAP's best candidate
#: and kept the track for 3 frames.
_BEFORE_WHOLE_CONFIG = {**_BEFORE_CHAINS, "candidates": {"bruteforce_fallback": 1, "track_memory": 3}}
