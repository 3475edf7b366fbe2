"""Pose-graph optimisation (gtsam): odometry chain + loop-closure edges under a robust kernel.

Nodes are camera-to-world poses T_w_k; an edge (a, b, T_a_b) says "frame b seen from frame a"
(gtsam BetweenFactorPose3: T_w_a^-1 T_w_b = T_a_b). Edge noise is diagonal in gtsam's Pose3
tangent order (rotation rad x, y, z, then translation m x, y, z). Loop edges go through a robust
kernel: a loop edge that disagrees with everything else loses its weight instead of bending the
trajectory. Frame 0 is fixed where the initial estimate puts it.

Kernels: "cauchy" (default), "huber", "none". They are M-estimators run by Levenberg-Marquardt
from the odometry, so a loop edge is weighed by its residual at the drifted start: at scale 1 a
Cauchy kernel mutes a TRUE loop that closes 0.4 m of drift (~13 sigma of the edge), at scale 3
it keeps it (near full weight) and still mutes an alias on the far side of the loop (weight
near zero); Huber lets that alias pull with bounded but steady force (tests/slam/test_pose_graph.py).
(gtsam's graduated non-convexity, GncLMOptimizer with TLS, rejected the alias too but returned
poses well off the plain solution in the same test; not used. Figures: docs/results.md, "SLAM".)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from aefabmap_runtime.errors import ConfigError

KERNELS = ("cauchy", "huber", "none")


@dataclass(frozen=True)
class Edge:
    """A relative-pose measurement T_a_b (4x4) between frames a and b with its 1-sigma noise.

    sigma_rot: radians per axis; sigma_trans: metres per axis; loop: a loop-closure edge
    (robust kernel), else an odometry edge (plain Gaussian).
    """

    a: int
    b: int
    T: np.ndarray
    sigma_rot: float
    sigma_trans: float
    loop: bool = False


@dataclass(frozen=True)
class PoseGraphConfig:
    """kernel: robust kernel of loop edges (KERNELS, see the module docstring); kernel_scale: its
    scale in standard deviations of the whitened residual (Cauchy: weight 1/2 at 3 sigma);
    max_iterations: Levenberg-Marquardt cap."""

    kernel: str = "cauchy"
    kernel_scale: float = 3.0
    max_iterations: int = 100

    def __post_init__(self) -> None:
        if self.kernel not in KERNELS:
            raise ConfigError(f"pose-graph kernel must be one of {KERNELS}, got {self.kernel!r}")
        if self.kernel_scale <= 0 or self.max_iterations < 1:
            raise ConfigError("pose-graph kernel_scale must be > 0 and max_iterations >= 1")


@dataclass
class PoseGraphResult:
    """poses (N, 4, 4) optimised camera-to-world; error before / after (gtsam's graph error);
    loop_weights: the robust kernel's weight of each loop edge at the solution (1: fully trusted)."""

    poses: np.ndarray
    initial_error: float
    final_error: float
    iterations: int
    loop_weights: list[float]


def _noise(gtsam, edge: Edge):
    sig = np.array([edge.sigma_rot] * 3 + [edge.sigma_trans] * 3)
    return gtsam.noiseModel.Diagonal.Sigmas(sig)


def _robust(gtsam, base, config: PoseGraphConfig):
    if config.kernel == "none":
        return base
    est = gtsam.noiseModel.mEstimator
    kernel = est.Cauchy.Create(config.kernel_scale) if config.kernel == "cauchy" else est.Huber.Create(config.kernel_scale)
    return gtsam.noiseModel.Robust.Create(kernel, base)


def optimize(initial: np.ndarray, edges: list[Edge], config: PoseGraphConfig | None = None) -> PoseGraphResult:
    """Optimise N poses (initial (N, 4, 4) camera-to-world) under the edges; frame 0 stays fixed."""
    import gtsam  # optional extra: aefabmap[slam]

    c = config or PoseGraphConfig()
    n = int(initial.shape[0])
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorPose3(0, gtsam.Pose3(initial[0]), gtsam.noiseModel.Constrained.All(6)))
    loop_factors = []
    for e in edges:
        if not (0 <= e.a < n and 0 <= e.b < n) or e.a == e.b:
            raise ConfigError(f"pose-graph edge ({e.a}, {e.b}) outside the {n} frames")
        noise = _noise(gtsam, e)
        factor = gtsam.BetweenFactorPose3(e.a, e.b, gtsam.Pose3(e.T), _robust(gtsam, noise, c) if e.loop else noise)
        graph.add(factor)
        if e.loop:
            loop_factors.append((factor, noise))
    values = gtsam.Values()
    for k in range(n):
        values.insert(k, gtsam.Pose3(initial[k]))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(c.max_iterations)
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    result = optimizer.optimize()
    weights = []
    for factor, noise in loop_factors:
        # Whitened residual of the edge at the solution, then the kernel's weight for it.
        r = np.asarray(factor.unwhitenedError(result))
        weights.append(_kernel_weight(c, float(np.linalg.norm(r / np.asarray(noise.sigmas())))))
    iterations, final = int(optimizer.iterations()), graph.error(result)
    poses = np.stack([result.atPose3(k).matrix() for k in range(n)])
    return PoseGraphResult(poses, float(graph.error(values)), float(final), iterations, weights)


def _kernel_weight(c: PoseGraphConfig, residual: float) -> float:
    """Weight the kernel gives a whitened residual (IRLS weight: 1 for an inlier)."""
    k = c.kernel_scale
    if c.kernel == "cauchy":
        return 1.0 / (1.0 + (residual / k) ** 2)
    if c.kernel == "huber":
        return 1.0 if residual <= k else k / residual
    return 1.0
