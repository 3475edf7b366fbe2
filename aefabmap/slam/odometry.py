"""Frame-to-frame RGB-D visual odometry: ORB matches, depth of the previous frame, PnP + RANSAC (OpenCV).

For frames k-1, k: ORB keypoints of both, mutual nearest-neighbour Hamming matches with a ratio
test, 3-D points of frame k-1 from its depth, then cv2.solvePnPRansac on frame k's keypoints and
a Levenberg-Marquardt refinement on the inliers. That gives T_k_{k-1} (frame k-1 -> frame k);
the camera-to-world pose is T_w_k = T_w_{k-1} T_{k-1}_k. When frame k-1 does not give enough
inliers, frame k-2 is tried (one skipped frame); then guided matching against frame k-1 (its
3-D points projected with the previous motion, matches searched within `guided_radius_px` of the
projection, which makes the ratio test local: little texture, repeated corners); when nothing
works, the previous motion is repeated (constant velocity) and the step is flagged as failed.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import cv2
import numpy as np

from aefabmap_runtime.errors import ConfigError
from aefabmap_runtime.core.kernels.bits import hamming, nearest_two
from aefabmap.slam.poses import invert, make_pose


@dataclass(frozen=True)
class OdometryConfig:
    """Settings of the visual odometry.

    max_features: ORB keypoints per frame (more than the loop detector's 500: frames are far
        apart and texture is scarce, so the odometry needs every corner).
    fast_threshold: ORB's FAST threshold (OpenCV default 20; lower finds corners on weak texture).
    ratio: nearest / second-nearest Hamming distance of a match.
    max_hamming: largest Hamming distance (bits of 256) of a match.
    min_depth / max_depth: depth range trusted, metres (the Kinect-class sensor's useful range).
    reprojection_px: RANSAC inlier threshold, pixels.
    min_inliers: a PnP result with fewer inliers is not trusted.
    iterations: RANSAC iterations.
    guided_radius_px: search radius of guided matching around the predicted position, pixels
        (0 disables it); the radius covers how far the prediction (constant velocity) lands off
        when the rotation between frames changes abruptly (docs/results.md, "SLAM").
    """

    max_features: int = 4000
    fast_threshold: int = 5
    ratio: float = 0.9
    max_hamming: int = 64
    min_depth: float = 0.2
    max_depth: float = 6.0
    reprojection_px: float = 3.0
    min_inliers: int = 15
    iterations: int = 2000
    guided_radius_px: float = 100.0

    def __post_init__(self) -> None:
        if self.max_features < 50 or self.min_inliers < 6 or self.reprojection_px <= 0:
            raise ConfigError("odometry needs max_features >= 50, min_inliers >= 6, reprojection_px > 0")
        if not (0 < self.ratio <= 1) or not (0 < self.min_depth < self.max_depth):
            raise ConfigError("odometry needs 0 < ratio <= 1 and 0 < min_depth < max_depth")


@dataclass
class FrameFeatures:
    """ORB keypoints (N, 2) float32 pixels and descriptors (N, 32) uint8 of one frame, with its depth (H, W) metres."""

    xy: np.ndarray
    desc: np.ndarray
    depth: np.ndarray


@dataclass
class RelativePose:
    """T_a_b (4x4: frame b -> frame a) from PnP, with its support; T is None when PnP failed."""

    T: np.ndarray | None
    inliers: int = 0
    matches: int = 0


@dataclass
class OdometryResult:
    """poses (N, 4, 4) camera-to-world, frame 0 at the identity; steps[k] the PnP behind frame k
    (k >= 1; its reference frame in `reference`), `failed` the frames where the motion was guessed."""

    poses: np.ndarray
    steps: list[RelativePose]
    reference: list[int]
    failed: list[int] = field(default_factory=list)
    ms_per_frame: float = 0.0


class OrbExtractor:
    """ORB keypoints and descriptors of grayscale images (OpenCV)."""

    def __init__(self, config: OdometryConfig) -> None:
        self.orb = cv2.ORB_create(nfeatures=config.max_features, fastThreshold=config.fast_threshold)

    def __call__(self, gray: np.ndarray, depth: np.ndarray) -> FrameFeatures:
        kps, desc = self.orb.detectAndCompute(gray, None)
        if desc is None or not kps:
            return FrameFeatures(np.zeros((0, 2), np.float32), np.zeros((0, 32), np.uint8), depth)
        return FrameFeatures(np.array([k.pt for k in kps], np.float32), desc, depth)


def match_orb(desc_a: np.ndarray, desc_b: np.ndarray, ratio: float, max_hamming: int) -> np.ndarray:
    """Mutual nearest-neighbour Hamming matches passing the ratio test: (M, 2) int rows (index in a, index in b)."""
    if len(desc_a) < 2 or len(desc_b) < 2:
        return np.zeros((0, 2), np.int64)
    d_ab, i_ab = nearest_two(desc_a, desc_b)
    _, i_ba = nearest_two(desc_b, desc_a)
    a = np.arange(len(desc_a))
    b = i_ab[:, 0]
    keep = (d_ab[:, 0] <= max_hamming) & (d_ab[:, 0] < ratio * d_ab[:, 1]) & (b >= 0)
    keep &= i_ba[np.clip(b, 0, None), 0] == a  # mutual
    return np.stack([a[keep], b[keep]], axis=1).astype(np.int64)


def backproject(xy: np.ndarray, depth: np.ndarray, K: np.ndarray, min_depth: float, max_depth: float
                ) -> tuple[np.ndarray, np.ndarray]:
    """3-D points (M, 3) in the camera frame of pixels xy (N, 2) with valid depth, and the mask (N,) of those pixels."""
    h, w = depth.shape
    u = np.clip(np.round(xy[:, 0]).astype(int), 0, w - 1)
    v = np.clip(np.round(xy[:, 1]).astype(int), 0, h - 1)
    z = depth[v, u].astype(np.float64)
    ok = (z >= min_depth) & (z <= max_depth)
    x = (xy[ok, 0] - K[0, 2]) * z[ok] / K[0, 0]
    y = (xy[ok, 1] - K[1, 2]) * z[ok] / K[1, 1]
    return np.stack([x, y, z[ok]], axis=1), ok


def camera_points(points: np.ndarray, T: np.ndarray) -> np.ndarray:
    """3-D points (N, 3) moved by the 4x4 pose T: (N, 3) in T's target camera frame."""
    return points @ T[:3, :3].T + T[:3, 3]


def to_pixels(cam: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Camera-frame points (N, 3), z > 0, -> (N, 2) pixels through the pinhole K."""
    return cam[:, :2] / cam[:, 2:] * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]


def pnp_pose(points_b: np.ndarray, xy_a: np.ndarray, K: np.ndarray, config: OdometryConfig) -> RelativePose:
    """T_a_b from 3-D points (M, 3) in frame b seen at pixels xy_a (M, 2) of frame a: RANSAC, then LM on the inliers."""
    m = int(points_b.shape[0])
    if m < max(config.min_inliers, 6):
        return RelativePose(None, 0, m)
    obj = np.ascontiguousarray(points_b, np.float64)
    img = np.ascontiguousarray(xy_a, np.float64)
    try:
        ok, rvec, tvec, inl = cv2.solvePnPRansac(obj, img, K, None, iterationsCount=config.iterations,
                                                 reprojectionError=config.reprojection_px, confidence=0.999,
                                                 flags=cv2.SOLVEPNP_EPNP)
    except cv2.error:
        return RelativePose(None, 0, m)
    if not ok or inl is None or len(inl) < config.min_inliers:
        return RelativePose(None, 0 if inl is None else len(inl), m)
    inl = inl.ravel()
    rvec, tvec = cv2.solvePnPRefineLM(obj[inl], img[inl], K, None, rvec, tvec)
    # Inliers again under the refined pose (the refinement may move some in or out).
    proj, _ = cv2.projectPoints(obj, rvec, tvec, K, None)
    err = np.linalg.norm(proj.reshape(-1, 2) - img, axis=1)
    n_in = int((err <= config.reprojection_px).sum())
    if n_in < config.min_inliers:
        return RelativePose(None, n_in, m)
    R, _ = cv2.Rodrigues(rvec)
    return RelativePose(make_pose(R, tvec.ravel()), n_in, m)


def relative_pose(feat_a: FrameFeatures, feat_b: FrameFeatures, K: np.ndarray, config: OdometryConfig) -> RelativePose:
    """T_a_b between two frames: matches, 3-D points of b from its depth, PnP on a's keypoints."""
    pairs = match_orb(feat_a.desc, feat_b.desc, config.ratio, config.max_hamming)
    if pairs.shape[0] == 0:
        return RelativePose(None, 0, 0)
    pts, ok = backproject(feat_b.xy[pairs[:, 1]], feat_b.depth, K, config.min_depth, config.max_depth)
    return pnp_pose(pts, feat_a.xy[pairs[ok, 0]], K, config)


def guided_pose(feat_a: FrameFeatures, feat_b: FrameFeatures, T_ab_guess: np.ndarray, K: np.ndarray,
                config: OdometryConfig, chunk: int = 256) -> RelativePose:
    """T_a_b by guided matching: b's 3-D points projected into a with T_ab_guess, each matched to the
    nearest-descriptor keypoint of a within guided_radius_px (ratio test within that window), then PnP."""
    pts, ok = backproject(feat_b.xy, feat_b.depth, K, config.min_depth, config.max_depth)
    desc_b = feat_b.desc[ok]
    cam = camera_points(pts, T_ab_guess)
    front = cam[:, 2] > config.min_depth
    pts, cam, desc_b = pts[front], cam[front], desc_b[front]
    if len(pts) < config.min_inliers or len(feat_a.xy) < 2:
        return RelativePose(None)
    uv = to_pixels(cam, K)
    best = np.full(len(pts), -1, np.int64)
    d1 = np.full(len(pts), np.inf, np.float32)
    for s in range(0, len(pts), chunk):  # chunks bound the (chunk, N_a, 32) Hamming table to ~32 MB
        e = min(s + chunk, len(pts))
        D = hamming(desc_b[s:e, None, :], feat_a.desc[None, :, :]).astype(np.float32)
        far = np.linalg.norm(uv[s:e, None, :] - feat_a.xy[None, :, :], axis=2) > config.guided_radius_px
        D[far] = np.inf
        two = np.argpartition(D, 1, axis=1)[:, :2]
        dd = np.take_along_axis(D, two, axis=1)
        order = np.argsort(dd, axis=1)
        two, dd = np.take_along_axis(two, order, axis=1), np.take_along_axis(dd, order, axis=1)
        keep = (dd[:, 0] <= config.max_hamming) & (dd[:, 0] < config.ratio * dd[:, 1])
        best[s:e] = np.where(keep, two[:, 0], -1)
        d1[s:e] = dd[:, 0]
    rows = np.flatnonzero(best >= 0)
    # One-to-one: each keypoint of a keeps its closest point of b.
    rows = rows[np.lexsort((d1[rows], best[rows]))]
    rows = rows[np.r_[True, best[rows][1:] != best[rows][:-1]]] if rows.size else rows
    return pnp_pose(pts[rows], feat_a.xy[best[rows]], K, config)


def run_odometry(frames, K: np.ndarray, config: OdometryConfig | None = None) -> OdometryResult:
    """Visual odometry over an iterable of (gray (H, W) uint8, depth (H, W) metres) frames."""
    c = config or OdometryConfig()
    extract = OrbExtractor(c)
    poses: list[np.ndarray] = []
    steps: list[RelativePose] = [RelativePose(np.eye(4))]
    reference = [0]
    failed: list[int] = []
    history: list[FrameFeatures] = []
    velocity = np.eye(4)  # T_{k-1}_k of the last step
    t0 = time.perf_counter()
    for k, (gray, depth) in enumerate(frames):
        feat = extract(gray, depth)
        if k == 0:
            poses.append(np.eye(4))
        else:
            step, ref = RelativePose(None), k - 1
            for back in (1, 2):  # the previous frame, then the one before it
                if k - back < 0:
                    break
                step = relative_pose(feat, history[-back], K, c)
                if step.T is not None:
                    ref = k - back
                    break
            if step.T is None and c.guided_radius_px > 0:
                step, ref = guided_pose(feat, history[-1], invert(velocity), K, c), k - 1
            if step.T is None:
                failed.append(k)
                poses.append(poses[-1] @ velocity)
                ref = k - 1
            else:
                poses.append(poses[ref] @ invert(step.T))
                velocity = invert(poses[k - 1]) @ poses[k]
            steps.append(step)
            reference.append(ref)
        history = (history + [feat])[-2:]
    n = max(len(poses), 1)
    return OdometryResult(np.stack(poses), steps, reference, failed, (time.perf_counter() - t0) * 1e3 / n)
