"""PinholeCamera's compiled Newton undistortion gives the vectorised numpy iteration's points bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

from slamkit.geometry.camera import _MAX_NEWTON_ITERS, PinholeCamera


def _numpy_newton(cam: PinholeCamera, xd: np.ndarray, yd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The numpy iteration the kernel replaced (camera.py before it), kept here as the reference."""
    k1, k2, p1, p2, k3 = cam.dist
    x, y = xd.copy(), yd.copy()
    finite = np.isfinite(xd) & np.isfinite(yd)
    x[~finite] = 0.0
    y[~finite] = 0.0
    for _ in range(_MAX_NEWTON_ITERS):
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dradial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
        ex = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) - xd
        ey = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y - yd
        j11 = radial + 2.0 * x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x
        j12 = 2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y
        j22 = radial + 2.0 * y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x
        det = j11 * j22 - j12 * j12
        with np.errstate(invalid="ignore", divide="ignore"):
            dx = (j22 * ex - j12 * ey) / det
            dy = (j11 * ey - j12 * ex) / det
        dx[~np.isfinite(dx)] = 0.0
        dy[~np.isfinite(dy)] = 0.0
        x -= dx
        y -= dy
        if np.all(np.abs(dx) + np.abs(dy) <= 1e-15 * (1.0 + np.abs(x) + np.abs(y))):
            break
    return x, y


@pytest.mark.parametrize(
    "dist",
    [
        [0.262383, -0.953104, -0.005358, 0.002628, 1.163314],  # TUM fr1 (ORB-SLAM's TUM1.yaml)
        [-0.4, 0.1, 0.001, -0.002, 0.0],  # strong barrel
        [0.0, 0.0, 0.01, -0.01, 0.0],  # tangential only
    ],
)
def test_compiled_undistortion_is_the_numpy_iteration(dist: list[float]) -> None:
    cam = PinholeCamera(640, 480, 517.3, 516.5, 318.6, 255.3, dist)
    rng = np.random.default_rng(7)
    uv = np.column_stack([rng.uniform(-40, 680, 3000), rng.uniform(-40, 520, 3000)])
    uv[:3] = [[np.nan, 10.0], [np.inf, 5.0], [1e9, -1e9]]  # not finite; far outside the model's one-to-one region
    xd, yd = cam._to_normalized(uv)
    x_ref, y_ref = _numpy_newton(cam, xd, yd)
    x, y = cam._undistort(xd, yd)
    ok = np.isfinite(x)
    assert ok.sum() > 2500 and not ok[:2].any()
    assert x[ok].tobytes() == x_ref[ok].tobytes() and y[ok].tobytes() == y_ref[ok].tobytes()
    assert np.array_equal(np.isfinite(x), np.isfinite(y))
