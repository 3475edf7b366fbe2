"""Is a two-view model well conditioned? Degeneracy tests for F, E and H (pure numpy).

A robust estimator returns *a* model for any input, including models that explain matches
without any two-view geometry: a fundamental matrix of rank 1 (x_q^T u v^T x_p = 0 only asks
each point to lie on one line per image), a numerically null matrix (every error ~0), a
homography that folds the image over or crushes it onto a line. These tests reject such
models before their inliers are counted.
"""

from __future__ import annotations

import numpy as np


def normalising_transform(points: np.ndarray) -> np.ndarray:
    """(3, 3) similarity moving points (K, 2) to centroid 0 and mean distance sqrt(2) (Hartley)."""
    centre = points.mean(axis=0)
    d = points - centre
    spread = float(np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1]).mean())
    s = np.sqrt(2.0) / max(spread, 1e-9)
    return np.array([[s, 0.0, -s * centre[0]], [0.0, s, -s * centre[1]], [0.0, 0.0, 1.0]])


def _similarity_inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of a `normalising_transform` matrix (scale s, translation t): scale 1/s, translation -t/s."""
    s = T[0, 0]
    return np.array([[1.0 / s, 0.0, -T[0, 2] / s], [0.0, 1.0 / s, -T[1, 2] / s], [0.0, 0.0, 1.0]])


def enforce_rank2(F: np.ndarray) -> np.ndarray:
    """Closest rank-2 matrix to F (Frobenius), scaled to unit norm; zeros for a null F."""
    u, s, vt = np.linalg.svd(F)
    if not np.isfinite(s[0]) or s[0] < 1e-300:
        return np.zeros((3, 3))
    F2 = (u[:, :2] * s[:2]) @ vt[:2]
    return F2 / np.linalg.norm(F2)


def rank2_fundamental(F: np.ndarray, xq: np.ndarray, xp: np.ndarray) -> tuple[np.ndarray, float]:
    """Closest rank-2 matrix to F (unit Frobenius norm) and sigma2 / sigma1 of F in normalised coordinates.

    F relates xp -> xq (x_q^T F x_p = 0); xq, xp (K, 2): the matched points, which define the
    Hartley normalisation (so the ratio does not depend on the image size or origin). A
    well-posed two-view geometry has two comparable non-zero singular values (an essential
    matrix: two equal ones); a ratio near 0 means F is (numerically) rank 1 or null.
    """
    norm = np.linalg.norm(F)
    if not np.isfinite(norm) or norm < 1e-300:
        return np.zeros((3, 3)), 0.0
    Tq, Tp = normalising_transform(xq), normalising_transform(xp)
    # x_q^T F x_p = (Tq x_q)^T [Tq^-T F Tp^-1] (Tp x_p).
    Fn = _similarity_inverse(Tq).T @ (F / norm) @ _similarity_inverse(Tp)
    u, s, vt = np.linalg.svd(Fn)
    ratio = float(s[1] / s[0]) if s[0] > 0 else 0.0
    Fn2 = u @ np.diag([s[0], s[1], 0.0]) @ vt
    F2 = Tq.T @ Fn2 @ Tp
    return F2 / max(np.linalg.norm(F2), 1e-300), ratio


def homography_jacobians(H: np.ndarray, xp: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Local linear maps of H at points xp (K, 2): (K, 2, 2) Jacobians and (K,) depths w = h3 . x."""
    x, y = xp[:, 0], xp[:, 1]
    w = H[2, 0] * x + H[2, 1] * y + H[2, 2]
    safe = np.where(np.abs(w) > 1e-12, w, 1e-12)
    u = (H[0, 0] * x + H[0, 1] * y + H[0, 2]) / safe
    v = (H[1, 0] * x + H[1, 1] * y + H[1, 2]) / safe
    J = np.empty((xp.shape[0], 2, 2))
    J[:, 0, 0] = (H[0, 0] - H[2, 0] * u) / safe
    J[:, 0, 1] = (H[0, 1] - H[2, 1] * u) / safe
    J[:, 1, 0] = (H[1, 0] - H[2, 0] * v) / safe
    J[:, 1, 1] = (H[1, 1] - H[2, 1] * v) / safe
    return J, w


def homography_is_plausible(H: np.ndarray, xp: np.ndarray, max_scale: float, max_anisotropy: float) -> bool:
    """A homography a camera could produce between the points xp (K, 2) and their images.

    At every point: the depth w keeps one sign (no point crosses the horizon line) and the
    local map preserves orientation (det J > 0: a camera sees no mirror image). Typical over
    the points (median: a plane seen in perspective legitimately stretches near its horizon):
    the linear scale sqrt(det J) lies in [1/max_scale, max_scale] and the two singular values
    of J differ by at most max_anisotropy (a near-singular H crushes a region onto a line).
    """
    if xp.shape[0] == 0 or not np.all(np.isfinite(H)):
        return False
    J, w = homography_jacobians(H, xp)
    if not (np.all(w > 0) or np.all(w < 0)):
        return False
    det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
    if np.any(det <= 0):
        return False
    scale = float(np.median(np.sqrt(det)))
    if not (1.0 / max_scale <= scale <= max_scale):
        return False
    # Singular values of a 2x2 map from its Frobenius norm and determinant (closed form).
    fro2 = (J * J).sum(axis=(1, 2))
    root = np.sqrt(np.maximum(fro2 * fro2 - 4.0 * det * det, 0.0))
    s1 = np.sqrt((fro2 + root) / 2.0)
    s2 = det / np.maximum(s1, 1e-12)
    return bool(np.median(s1 / np.maximum(s2, 1e-12)) <= max_anisotropy)


def minor_axis_extent(points: np.ndarray) -> float:
    """Standard deviation of points (K, 2) across their principal axis (0 for points on a line)."""
    if points.shape[0] < 3:
        return 0.0
    d = points - points.mean(axis=0)
    a, b, c = float(np.mean(d[:, 0] ** 2)), float(np.mean(d[:, 0] * d[:, 1])), float(np.mean(d[:, 1] ** 2))
    # Smaller eigenvalue of the 2x2 covariance [[a, b], [b, c]].
    small = 0.5 * (a + c) - np.sqrt(0.25 * (a - c) ** 2 + b * b)
    return float(np.sqrt(max(small, 0.0)))
