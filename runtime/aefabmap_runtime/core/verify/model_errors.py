"""Per-match errors of a two-view model: homography transfer and epipolar distances.

The a-contrario test (acontrario.py) ranks matches by these errors. Each has a numpy form and a
compiled form (runtime/aefabmap_runtime/core/kernels/compiled.py) that evaluates the same expressions point by point:
at the tens to hundreds of matches a candidate has, numpy's per-call overhead (a dozen array
passes) cost more than the arithmetic. The two forms agree to float64 rounding (numpy may fuse
a multiply-add inside its small matrix products); acceptance uses the errors only through
comparisons with thresholds and the NFA, so the choice changes speed only.
"""

from __future__ import annotations

import numpy as np

from aefabmap_runtime.core.kernels import compiled, native


def transfer_errors(H: np.ndarray, src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Larger of the forward (H: src -> dst) and backward (H^-1: dst -> src) transfer distances.

    H (3, 3); src, dst (K, 2) float64 points. Returns (K,) float64, inf where a distance is
    undefined (a point on the horizon line of H, or H singular).
    """
    try:
        Hi = np.linalg.inv(H)
    except np.linalg.LinAlgError:
        return np.full(src.shape[0], np.inf)
    if compiled.active() == "compiled" and src.dtype == np.float64 and dst.dtype == np.float64:
        out = np.empty(src.shape[0], np.float64)
        transfer_kernel()(np.ascontiguousarray(H, np.float64), np.ascontiguousarray(Hi, np.float64),
                          np.ascontiguousarray(src), np.ascontiguousarray(dst), out)
        return out
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        err = np.maximum(_transfer(H, src, dst), _transfer(Hi, dst, src))
    return np.where(np.isfinite(err), err, np.inf)


def _transfer(H: np.ndarray, src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Distance (K,) between H applied to src (K, 2) and dst (K, 2)."""
    x, y = src[:, 0], src[:, 1]
    w = H[2, 0] * x + H[2, 1] * y + H[2, 2]
    u = (H[0, 0] * x + H[0, 1] * y + H[0, 2]) / w - dst[:, 0]
    v = (H[1, 0] * x + H[1, 1] * y + H[1, 2]) / w - dst[:, 1]
    return np.sqrt(u * u + v * v)


@compiled.kernel(native.transfer_errors)
def transfer_kernel():
    """`transfer_errors` compiled: the same expressions per point; out (K,) is written."""
    def transfer(H, Hi, src, dst, out):
        for i in range(src.shape[0]):
            x, y, qx, qy = src[i, 0], src[i, 1], dst[i, 0], dst[i, 1]
            w = H[2, 0] * x + H[2, 1] * y + H[2, 2]
            u = (H[0, 0] * x + H[0, 1] * y + H[0, 2]) / w - qx
            v = (H[1, 0] * x + H[1, 1] * y + H[1, 2]) / w - qy
            forward = np.sqrt(u * u + v * v)
            w = Hi[2, 0] * qx + Hi[2, 1] * qy + Hi[2, 2]
            u = (Hi[0, 0] * qx + Hi[0, 1] * qy + Hi[0, 2]) / w - x
            v = (Hi[1, 0] * qx + Hi[1, 1] * qy + Hi[1, 2]) / w - y
            backward = np.sqrt(u * u + v * v)
            # As numpy's maximum then isfinite: a NaN or inf on either side gives inf.
            out[i] = max(forward, backward) if np.isfinite(forward) and np.isfinite(backward) else np.inf

    return compiled.numba.njit("void(float64[:, ::1], float64[:, ::1], float64[:, ::1], float64[:, ::1], float64[::1])",
                               nogil=True, cache=False, boundscheck=False, error_model="numpy")(transfer)


def epipolar_errors(F: np.ndarray, xq: np.ndarray, xp: np.ndarray) -> np.ndarray:
    """Larger of the two point-to-epipolar-line distances (K,) of matches xp -> xq under x_q^T F x_p = 0.

    The a-contrario test counts a match as explained only when both points lie near their
    lines. A line with (near) zero normal is undefined: its matches get an infinite error
    (never an inlier, unlike a clamped denominator, which makes a null F explain everything).
    """
    scale = max(float(np.linalg.norm(F)), 1e-300)
    if compiled.active() == "compiled" and xq.dtype == np.float64 and xp.dtype == np.float64:
        out = np.empty(xq.shape[0], np.float64)
        epipolar_kernel()(np.ascontiguousarray(F, np.float64), np.ascontiguousarray(xq), np.ascontiguousarray(xp),
                          1e-9 * scale, out)
        return out
    lq = xp @ F[:, :2].T + F[:, 2]  # lines F x_p in the query image, (K, 3)
    lp = xq @ F[:2, :] + F[2, :]  # lines F^T x_q in the place image
    num = np.abs(xq[:, 0] * lq[:, 0] + xq[:, 1] * lq[:, 1] + lq[:, 2])
    nq, np_ = np.hypot(lq[:, 0], lq[:, 1]), np.hypot(lp[:, 0], lp[:, 1])
    ok = (nq > 1e-9 * scale) & (np_ > 1e-9 * scale)
    with np.errstate(divide="ignore", invalid="ignore"):
        err = np.maximum(num / nq, num / np_)
    return np.where(ok & np.isfinite(err), err, np.inf)


@compiled.kernel(native.epipolar_errors)
def epipolar_kernel():
    """`epipolar_errors` compiled: the same expressions per match; out (K,) is written."""
    def epipolar(F, xq, xp, min_normal, out):
        for i in range(xq.shape[0]):
            qx, qy, px, py = xq[i, 0], xq[i, 1], xp[i, 0], xp[i, 1]
            a = px * F[0, 0] + py * F[0, 1] + F[0, 2]
            b = px * F[1, 0] + py * F[1, 1] + F[1, 2]
            c = px * F[2, 0] + py * F[2, 1] + F[2, 2]
            d = qx * F[0, 0] + qy * F[1, 0] + F[2, 0]
            e = qx * F[0, 1] + qy * F[1, 1] + F[2, 1]
            num = abs(qx * a + qy * b + c)
            nq, np_ = np.hypot(a, b), np.hypot(d, e)
            err = max(num / nq, num / np_) if nq > min_normal and np_ > min_normal else np.inf
            out[i] = err if np.isfinite(err) else np.inf

    return compiled.numba.njit("void(float64[:, ::1], float64[:, ::1], float64[:, ::1], float64, float64[::1])",
                               nogil=True, cache=False, boundscheck=False, error_model="numpy")(epipolar)
