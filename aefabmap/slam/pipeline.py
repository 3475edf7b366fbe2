"""`aefabmap slam`: odometry + aefabmap loop closures + pose graph on a TUM RGB-D folder, written and scored.

One pass over the frames runs the visual odometry (odometry.py) and the loop-closure detector
(runtime/aefabmap_runtime/core/detector.py, geometric verification with the camera's essential matrix) side by
side; each verified loop becomes an edge (loops.py); the pose graph (pose_graph.py) is optimised
once at the end. Outputs in OUT: odometry.txt and optimized.txt (TUM format), and with ground
truth metrics.json (evo ATE/RPE, loop edges checked against the ground truth) and trajectory.png.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from aefabmap_runtime.errors import ConfigError
from aefabmap_runtime.core.verify.acontrario import SAMPLE_SIZE
from aefabmap_runtime.core.records.messages import FrameResult
from aefabmap.slam.loops import LoopEdge, exclusion_frames, loop_edge, proposal_edge
from aefabmap.slam.odometry import OdometryConfig, OrbExtractor, run_odometry
from aefabmap.slam.pose_graph import Edge, PoseGraphConfig, optimize
from aefabmap.slam.poses import invert, pose_difference
from aefabmap.slam.tum_io import RgbdSequence, write_tum_trajectory


@dataclass(frozen=True)
class SlamConfig:
    """Settings of `aefabmap slam`.

    min_gap_s: a loop closure joins frames at least this far apart in time (the detector's
        exclusion window and insertion delay, converted to frames at the median frame interval):
        closer frames are the odometry's business. 10 s is the revisit definition of the TUM
        cabinet subsample's loop check (frame pairs >= 10 s apart).
    sigma_rot / sigma_trans: 1-sigma noise of a PnP edge with `reference_inliers` inliers
        (rad, m per axis); an edge with n inliers gets sigma * sqrt(reference_inliers / n) (a PnP
        estimate's covariance falls as 1/n). Order of magnitude of the odometry's per-step error
        on the TUM cabinet subsample, rounded up; not fitted (docs/slam.md, "Results: TUM fr3
        cabinet, 58-frame subsample").
    guess_sigma_rot / guess_sigma_trans: noise of a step the odometry could only guess (constant velocity).
    wrong_trans_m / wrong_rot_deg: a loop edge whose relative pose differs from the ground truth's
        by more than either is counted wrong: about one frame step of this data (docs/results.md,
        "SLAM").
    camera_verification: verify loops with the camera's essential matrix (else a fundamental matrix).
    min_inliers_h: the detector's floor on homography inliers (VerificationConfig.min_inliers_h,
        runtime default 8: a minimum support for a pose known only from two images). Here every
        loop edge's pose is re-estimated from the place's metric 3-D points by PnP, with its own
        floor (`OdometryConfig`), so the 2-D floor is redundant: the tool sets it to the least
        the a-contrario test can judge (one more than the 4-point sample), and significance
        (NFA < 1e-4) plus the 3-D check decide. For the same reason the detector counts
        neighbouring matches as separate evidence here (`VerificationConfig.independence` = 0;
        copies at one location still count once): the 2-D test only proposes loops, and a
        proposal becomes an edge only if the place's metric 3-D points confirm it. Not fitted to
        any sequence.
    proposals: when the two-view test gave a frame no edge, up to this many places are checked
        in 3-D (`loops.proposal_edge`, the detector's significance bar; `proposal_frames`: the
        two-view verified place first, then the detector's candidates by FAB-MAP rank); the
        first confirmed one becomes the frame's edge. 0: edges from two-view verified loops
        only. The detector's own top_k (5) by default: the places it would verify itself.
    """

    min_gap_s: float = 10.0
    odometry: OdometryConfig = field(default_factory=OdometryConfig)
    graph: PoseGraphConfig = field(default_factory=PoseGraphConfig)
    sigma_rot: float = 0.02
    sigma_trans: float = 0.03
    reference_inliers: int = 50
    guess_sigma_rot: float = 0.5
    guess_sigma_trans: float = 0.5
    wrong_trans_m: float = 0.2
    wrong_rot_deg: float = 10.0
    camera_verification: bool = True
    min_inliers_h: int = SAMPLE_SIZE["H"] + 1
    proposals: int = 5

    def __post_init__(self) -> None:
        if self.min_gap_s <= 0 or self.sigma_rot <= 0 or self.sigma_trans <= 0 or self.reference_inliers < 1:
            raise ConfigError("slam needs min_gap_s, sigma_rot, sigma_trans > 0 and reference_inliers >= 1")
        if not isinstance(self.proposals, int) or self.proposals < 0:
            raise ConfigError(f"slam proposals must be an integer >= 0, got {self.proposals!r}")


@dataclass
class SlamRun:
    """Everything one run produced (see `summary()` for the JSON)."""

    odometry: np.ndarray
    optimized: np.ndarray
    loop_edges: list[LoopEdge]
    verified_loops: int
    exclude: int
    odometry_failed: list[int]
    timings_ms: dict[str, float]
    loop_weights: list[float]
    metrics: dict = field(default_factory=dict)
    edge_checks: list[dict] = field(default_factory=list)
    run_config: dict | None = None  # the detector's RunConfig, whole (RunConfig.to_dict())
    proposals_tested: int = 0


def _sigma(config: SlamConfig, inliers: int) -> tuple[float, float]:
    s = float(np.sqrt(config.reference_inliers / max(inliers, 1)))
    return config.sigma_rot * s, config.sigma_trans * s


def run_slam(seq: RgbdSequence, bundle: str | Path, config: SlamConfig | None = None, *,
             show_progress: bool = False) -> SlamRun:
    """Odometry, loop edges from the bundle's detector, pose graph; no files written.
    show_progress: a tqdm bar on stderr for the pass over the frames and the one over the loop edges."""
    from tqdm import tqdm

    from aefabmap_runtime.adapters.bundle_reader import load_detector
    from aefabmap_runtime.core.detector import DetectorConfig
    from aefabmap_runtime.core.run_config import RunConfig
    from aefabmap_runtime.core.verify.verification import VerificationConfig

    c = config or SlamConfig()
    exclude = exclusion_frames(seq.stamps, c.min_gap_s)
    verification = VerificationConfig(keep_inlier_points=True, camera=seq.camera if c.camera_verification else None,
                                      min_inliers_h=c.min_inliers_h, independence=0.0)
    run_config = RunConfig(model=str(bundle), detector=DetectorConfig(exclude=exclude, verification=verification))
    detector = load_detector(bundle, run_config.detector)
    K = seq.K
    results, det_ms = [], []

    def frames():
        for i in tqdm(range(len(seq)), desc="frames", unit="frame", disable=not show_progress, mininterval=1.0):
            gray, depth = seq.gray(i), seq.depth_m(i)
            t0 = time.perf_counter()
            results.append(detector.process(gray, round(seq.stamps[i] * 1e9)))
            det_ms.append((time.perf_counter() - t0) * 1e3)
            yield gray, depth

    t0 = time.perf_counter()
    odo = run_odometry(frames(), K, c.odometry)
    wall = (time.perf_counter() - t0) * 1e3
    t1 = time.perf_counter()
    edges: list[LoopEdge] = []
    verified = tested = 0
    extractor = OrbExtractor(c.odometry)

    # A frame and its candidates recur over a few consecutive frames (a revisit proposes
    # neighbouring places); each entry holds a full depth map, so the cache is bounded, not per run.
    @functools.lru_cache(maxsize=2 * (c.proposals + 2))
    def features(i: int):
        return extractor(seq.gray(i), seq.depth_m(i))

    for res in tqdm(results, desc="loop edges", unit="frame", disable=not show_progress, mininterval=1.0):
        q = res.sequence
        if res.verified:
            verified += 1
            e = loop_edge(res, features(q), features(res.verified_frame), K, c.odometry)
            if e is not None:
                edges.append(e)
                if e.T_place_query is not None:
                    continue
        for place in proposal_frames(res, c.proposals):
            e = proposal_edge(q, place, features(q), features(place), K, c.odometry,
                              verification.max_log10_nfa, verification.duplicate_radius)
            tested += 1
            if e.T_place_query is not None:
                edges.append(e)
                break
    loop_ms = (time.perf_counter() - t1) * 1e3
    graph_edges = []
    for k in range(1, len(seq)):
        step, ref = odo.steps[k], odo.reference[k]
        if step.T is None:
            graph_edges.append(Edge(ref, k, invert(odo.poses[ref]) @ odo.poses[k], c.guess_sigma_rot, c.guess_sigma_trans))
        else:
            graph_edges.append(Edge(ref, k, invert(step.T), *_sigma(c, step.inliers)))
    for e in edges:
        if e.T_place_query is not None:
            graph_edges.append(Edge(e.place, e.query, e.T_place_query, *_sigma(c, e.pnp_inliers), loop=True))
    t2 = time.perf_counter()
    graph = optimize(odo.poses, graph_edges, c.graph)
    graph_ms = (time.perf_counter() - t2) * 1e3
    n = len(seq)
    odo_ms = wall - sum(det_ms)
    timings = {
        "odometry_per_frame": odo_ms / n,
        "detector_per_frame": float(np.mean(det_ms)),
        "loop_edges_per_frame": loop_ms / n,
        "pose_graph_total": graph_ms,
        "total_per_frame": (wall + loop_ms + graph_ms) / n,
    }
    return SlamRun(odo.poses, graph.poses, edges, verified, exclude, odo.failed, timings, graph.loop_weights,
                   proposals_tested=tested, run_config=run_config.to_dict())


def proposal_frames(res: FrameResult, limit: int) -> list[int]:
    """Places to check in 3-D for a frame whose two-view test gave no edge, at most `limit`, no
    repeats: the two-view verified place first (its few two-view inliers may not carry a PnP
    pose, while the 3-D check matches the frames' odometry features), then the detector's
    candidates by FAB-MAP rank."""
    order = [res.verified_frame] if res.verified and res.verified_frame is not None else []
    order += [cand.frame for cand in sorted(res.candidates, key=lambda cd: cd.rank)]
    return list(dict.fromkeys(order))[:limit]


def check_edges(run: SlamRun, gt: np.ndarray, config: SlamConfig) -> list[dict]:
    """Each loop edge against the ground truth's relative pose: errors and a `wrong` verdict."""
    out = []
    weights = iter(run.loop_weights)
    for e in run.loop_edges:
        row = {"query": e.query, "place": e.place, "source": e.source, "model": e.model,
               "verified_inliers": e.verified_inliers,
               "nfa": e.nfa, "seed_inliers": e.seed_inliers,
               "pnp_inliers": e.pnp_inliers, "edge": e.T_place_query is not None}
        G = invert(gt[e.place]) @ gt[e.query]
        if np.all(np.isfinite(G)):
            row["gt_distance_m"], row["gt_angle_deg"] = pose_difference(G, np.eye(4))
            if e.T_place_query is not None:
                dt, dr = pose_difference(e.T_place_query, G)
                row["error_m"], row["error_deg"] = dt, dr
                row["wrong"] = bool(dt > config.wrong_trans_m or dr > config.wrong_rot_deg)
        if e.T_place_query is not None:
            row["kernel_weight"] = next(weights)
        out.append(row)
    return out


def write_outputs(seq: RgbdSequence, run: SlamRun, out: str | Path, config: SlamConfig, bundle: str | Path,
                  plot: bool = True) -> dict:
    """Write odometry.txt, optimized.txt, metrics.json (+ trajectory.png with ground truth); returns the summary."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_tum_trajectory(out / "odometry.txt", seq.stamps, run.odometry)
    write_tum_trajectory(out / "optimized.txt", seq.stamps, run.optimized)
    summary = {
        "sequence": str(seq.root), "bundle": str(bundle), "frames": len(seq), "exclude_frames": run.exclude,
        "min_gap_s": config.min_gap_s, "kernel": config.graph.kernel, "odometry_failed": run.odometry_failed,
        "verified_loops": run.verified_loops,
        "proposals_tested": run.proposals_tested,
        "loop_edges": sum(e.T_place_query is not None for e in run.loop_edges),
        "loop_edges_from_proposals": sum(e.T_place_query is not None and e.source == "proposal" for e in run.loop_edges),
        "timings_ms": run.timings_ms, "load_average": os.getloadavg()[0] if hasattr(os, "getloadavg") else None,
        "config": dataclasses.asdict(config),
        "run_config": run.run_config,
    }
    gt = seq.groundtruth
    if gt is not None and np.isfinite(gt).all(axis=(1, 2)).sum() >= 3:
        from aefabmap.slam.metrics import aligned, trajectory_errors

        ok = np.isfinite(gt).all(axis=(1, 2))
        summary["odometry"] = trajectory_errors(seq.stamps, run.odometry, seq.stamps[ok], gt[ok]).to_dict()
        summary["optimized"] = trajectory_errors(seq.stamps, run.optimized, seq.stamps[ok], gt[ok]).to_dict()
        run.edge_checks = check_edges(run, gt, config)
        summary["loop_edge_checks"] = run.edge_checks
        summary["wrong_loop_edges"] = sum(bool(r.get("wrong")) for r in run.edge_checks)
        if plot:
            from aefabmap.slam.plot import plot_top_view

            odo_al, ref = aligned(seq.stamps, run.odometry, seq.stamps[ok], gt[ok])
            opt_al, _ = aligned(seq.stamps, run.optimized, seq.stamps[ok], gt[ok])
            pairs = [(e.place, e.query) for e in run.loop_edges if e.T_place_query is not None]
            title = (f"ATE RMSE: odometry {summary['odometry']['ate_rmse_m']:.3f} m, "
                     f"optimised {summary['optimized']['ate_rmse_m']:.3f} m ({summary['loop_edges']} loop edges)")
            plot_top_view(out / "trajectory.png", {"ground truth": ref, "odometry": odo_al, "optimised": opt_al},
                          pairs if ok.all() else None, opt_al if ok.all() else None, title)
    (out / "metrics.json").write_text(json.dumps(summary, indent=2) + "\n")
    return summary
