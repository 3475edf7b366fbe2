"""`aefabmap slam`: trajectory of a TUM RGB-D folder with aefabmap's loop closures (extra aefabmap[slam])."""

from __future__ import annotations

import json
from pathlib import Path

from aefabmap_runtime.errors import ConfigError


def register(sub) -> None:
    p = sub.add_parser("slam", help="RGB-D odometry + loop closures + pose graph on a TUM folder (needs aefabmap[slam])")
    src = p.add_argument_group("input")
    src.add_argument("--rgbd", required=True, type=Path, metavar="DIR",
                     help="TUM RGB-D folder: rgb.txt + depth.txt or associations.txt, camera.yaml, groundtruth.txt (optional)")
    src.add_argument("--model", required=True, type=Path, metavar="BUNDLE", help="model bundle directory (the detector's)")
    src.add_argument("--camera", default=None, metavar="FX,FY,CX,CY", help="intrinsics (default: DIR/camera.yaml)")
    loops = p.add_argument_group("loop edges and pose graph")
    loops.add_argument("--min-gap-s", type=float, default=10.0,
                       help="loops join frames at least this many seconds apart (default 10)")
    loops.add_argument("--min-inliers-h", type=int, default=None, metavar="N",
                       help="detector's floor on homography inliers of a loop (runtime default 8; here 5: every edge "
                       "is re-checked in 3-D by PnP, see docs/slam.md)")
    loops.add_argument("--proposals", type=int, default=None, metavar="N",
                       help="when the two-view test gives a frame no edge, check up to N of the detector's candidates "
                       "in 3-D (default 5, the detector's top_k; 0: verified loops only; see docs/slam.md)")
    loops.add_argument("--kernel", choices=("cauchy", "huber", "none"), default="cauchy",
                       help="robust kernel of the loop edges (default cauchy, scale 3 sigma)")
    out = p.add_argument_group("output")
    out.add_argument("--out", required=True, type=Path, metavar="DIR",
                     help="writes odometry.txt, optimized.txt (TUM format), metrics.json, trajectory.png")
    out.add_argument("--no-plot", action="store_true", help="skip trajectory.png")
    out.add_argument("--no-progress", action="store_true", help="no progress bars on stderr")
    p.set_defaults(func=run)


def _require_extra() -> None:
    missing = []
    for name in ("gtsam", "evo"):
        try:
            __import__(name)
        except ImportError:
            missing.append(name)
    if missing:
        raise ConfigError(f"aefabmap slam needs {', '.join(missing)}: pip install 'aefabmap[slam]'")


def run(args) -> int:
    _require_extra()
    from aefabmap_runtime.core.verify.verification import parse_camera
    from aefabmap.slam.pipeline import SlamConfig, run_slam, write_outputs
    from aefabmap.slam.pose_graph import PoseGraphConfig
    from aefabmap.slam.tum_io import read_rgbd_folder

    camera = parse_camera(args.camera) if args.camera else None
    extra = {} if args.min_inliers_h is None else {"min_inliers_h": args.min_inliers_h}
    if args.proposals is not None:
        extra["proposals"] = args.proposals
    config = SlamConfig(min_gap_s=args.min_gap_s, graph=PoseGraphConfig(kernel=args.kernel), **extra)
    seq = read_rgbd_folder(args.rgbd, camera)
    run_ = run_slam(seq, args.model, config, show_progress=not args.no_progress)
    summary = write_outputs(seq, run_, args.out, config, args.model, plot=not args.no_plot)
    brief = {k: v for k, v in summary.items() if k not in ("config", "loop_edge_checks")}
    print(json.dumps(brief, indent=2))
    return 0



