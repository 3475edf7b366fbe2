"""Per-match model errors: both forms (compiled, numpy) give the same errors, infinities included."""

from __future__ import annotations

import numpy as np

from aefabmap_runtime.core.verify.model_errors import epipolar_errors, transfer_errors


def _points(seed: int, n: int = 300) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return rng.uniform(0, 640, (n, 2)), rng.uniform(0, 480, (n, 2))


def test_transfer_errors_measure_both_directions(kernels):
    """A pure translation by (3, 4) moves every point 5 px each way; a point on H's horizon line
    (w = 0) has no image: inf, never NaN."""
    H = np.array([[1.0, 0, 3], [0, 1, 4], [0, 0, 1]])
    src = np.array([[10.0, 20.0], [0.0, 0.0]])
    dst = src + [3.0, 4.0]
    assert np.allclose(transfer_errors(H, src, dst), 0.0)
    assert np.allclose(transfer_errors(H, src, src), 5.0)
    horizon = np.array([[1.0, 0, 0], [0, 1, 0], [1e-2, 0, 1]])  # w = 0 at x = -100
    err = transfer_errors(horizon, np.array([[-100.0, 5.0], [1.0, 1.0]]), np.array([[0.0, 0.0], [1.0, 1.0]]))
    assert np.isinf(err[0]) and np.isfinite(err[1])
    assert np.all(np.isinf(transfer_errors(np.zeros((3, 3)), src, dst)))  # singular: no inverse


def test_compiled_and_numpy_errors_agree(on_both_paths):
    """Random models and points, plus the undefined cases: equal to float64 rounding, and inf
    in exactly the same places."""
    rng = np.random.default_rng(7)
    for seed in range(20):
        src, dst = _points(seed)
        H = np.eye(3) + rng.normal(0, [[0.1, 0.1, 20], [0.1, 0.1, 20], [1e-4, 1e-4, 0.05]])
        F = rng.normal(size=(3, 3))
        for fn, args in ((transfer_errors, (H, src, dst)), (epipolar_errors, (F, dst, src))):
            a, b = on_both_paths(lambda: fn(*args))
            assert a.dtype == b.dtype == np.float64 and a.shape == b.shape == (src.shape[0],)
            assert np.array_equal(np.isinf(a), np.isinf(b))
            finite = np.isfinite(a)
            assert np.allclose(a[finite], b[finite], rtol=1e-12, atol=1e-9)
    # A null F leaves every line undefined; a NaN point gives inf, not NaN.
    src, dst = _points(1, 5)
    src[2] = np.nan
    for a in on_both_paths(lambda: epipolar_errors(np.zeros((3, 3)), dst, src)):
        assert np.all(np.isinf(a))
    for a in [*on_both_paths(lambda: epipolar_errors(F, dst, src)),
              *on_both_paths(lambda: transfer_errors(np.eye(3), src, dst))]:
        assert np.isinf(a[2]) and np.all(np.isfinite(np.delete(a, 2)))
