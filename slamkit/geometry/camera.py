"""Central camera models: pinhole with radial-tangential distortion, and Kannala-Brandt fisheye.

Both satisfy ``slamkit.interfaces.Camera``. Pixel coordinates follow OpenCV: the centre of the top-left
pixel is (0, 0), u goes right and v down; the camera frame is x right, y down, z forward. All methods are
vectorised: they take (N, 2) / (N, 3) arrays (or a single (2,) / (3,) point, giving a single point back)
and return float64.

Where a model has no answer, methods return NaN rather than a wrong number: a pinhole cannot image points
with z <= 0, and a distortion polynomial is only a valid (one-to-one) model up to the first radius where it
folds back (its derivative vanishes); points beyond it are NaN in both directions.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numba
import numpy as np
from numpy.typing import NDArray

from slamkit.errors import ConfigError
from slamkit.geometry._checks import F64, as_points

__all__ = ["KannalaBrandtCamera", "PinholeCamera", "camera_from_config"]

# Newton iterations for undistortion; quadratic convergence needs ~5 for realistic lenses.
_MAX_NEWTON_ITERS = 50
# A solution whose re-distorted pixel misses the input by more than this is rejected (NaN).
_RESIDUAL_TOL_PX = 1e-7


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _newton_undistort(
    xd: F64, yd: F64, x: F64, y: F64, k1: float, k2: float, p1: float, p2: float, k3: float, max_iters: int
) -> None:  # pragma: no cover - numba
    """Newton's method on the 2x2 system distort(x, y) = (xd, yd) (radial k1 k2 k3, tangential p1 p2), for every point
    at once: x, y (N,) (the start, finite) are updated in place. Each iteration updates every point, and the loop
    stops when every step is below 1e-15 relative (or after ``max_iters``): the vectorised numpy iteration this
    replaced, operation for operation (same results bit for bit: no fused multiply-add without fastmath), without its
    per-iteration temporaries and with the GIL released. A step that is not finite (a singular Jacobian) is 0."""
    n = x.shape[0]
    dx = np.empty(n)
    dy = np.empty(n)
    for _ in range(max_iters):
        for i in range(n):
            xi, yi = x[i], y[i]
            r2 = xi * xi + yi * yi
            radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
            dradial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d radial / d r^2
            ex = xi * radial + 2.0 * p1 * xi * yi + p2 * (r2 + 2.0 * xi * xi) - xd[i]
            ey = yi * radial + p1 * (r2 + 2.0 * yi * yi) + 2.0 * p2 * xi * yi - yd[i]
            j11 = radial + 2.0 * xi * xi * dradial + 2.0 * p1 * yi + 6.0 * p2 * xi
            j12 = 2.0 * xi * yi * dradial + 2.0 * p1 * xi + 2.0 * p2 * yi
            j22 = radial + 2.0 * yi * yi * dradial + 6.0 * p1 * yi + 2.0 * p2 * xi
            det = j11 * j22 - j12 * j12
            sx = (j22 * ex - j12 * ey) / det
            sy = (j11 * ey - j12 * ex) / det
            dx[i] = sx if np.isfinite(sx) else 0.0
            dy[i] = sy if np.isfinite(sy) else 0.0
        converged = True
        for i in range(n):
            x[i] -= dx[i]
            y[i] -= dy[i]
            if not (abs(dx[i]) + abs(dy[i]) <= 1e-15 * (1.0 + abs(x[i]) + abs(y[i]))):
                converged = False
        if converged:
            return


# ----------------------------------------------------------------------------------------------------
# Parameter validation (messages name the config key: "camera.fx: expected a positive number, got -3")


def _is_real(value: Any) -> bool:
    return isinstance(value, int | float | np.integer | np.floating) and not isinstance(value, bool | np.bool_)


def _positive_number(value: Any, key: str) -> float:
    if not _is_real(value) or not math.isfinite(float(value)) or float(value) <= 0.0:
        raise ConfigError(f"{key}: expected a positive number, got {value!r}")
    return float(value)


def _finite_number(value: Any, key: str) -> float:
    if not _is_real(value) or not math.isfinite(float(value)):
        raise ConfigError(f"{key}: expected a finite number, got {value!r}")
    return float(value)


def _positive_int(value: Any, key: str) -> int:
    if not _is_real(value) or not math.isfinite(float(value)) or float(value) != int(value) or int(value) <= 0:
        raise ConfigError(f"{key}: expected a positive integer, got {value!r}")
    return int(value)


def _coefficients(value: Any, key: str, lengths: tuple[int, ...]) -> NDArray[np.float64]:
    if isinstance(value, str | bytes) or not isinstance(value, Sequence | np.ndarray):
        raise ConfigError(f"{key}: expected a list of {' or '.join(map(str, lengths))} numbers, got {value!r}")
    items = list(np.asarray(value, dtype=object).ravel()) if isinstance(value, np.ndarray) else list(value)
    if len(items) not in lengths:
        raise ConfigError(f"{key}: expected {' or '.join(map(str, lengths))} coefficients, got {len(items)}: {items!r}")
    return np.array([_finite_number(c, f"{key}[{i}]") for i, c in enumerate(items)], dtype=np.float64)


def _first_positive_root(coeffs_low_first: Sequence[float]) -> float:
    """Smallest positive real root of a polynomial (coefficients lowest degree first), or inf."""
    c = np.trim_zeros(np.asarray(coeffs_low_first, dtype=np.float64), "b")
    if c.size <= 1:
        return math.inf
    roots = np.polynomial.polynomial.polyroots(c)
    real = roots.real[(np.abs(roots.imag) <= 1e-9 * np.maximum(1.0, np.abs(roots.real))) & (roots.real > 0)]
    return float(real.min()) if real.size else math.inf


def _unit(v: F64) -> F64:
    with np.errstate(invalid="ignore", divide="ignore"):
        out: F64 = v / np.linalg.norm(v, axis=1, keepdims=True)
    return out


def _finish(points: F64, single: bool) -> F64:
    return points[0] if single else points


class _CameraBase:
    """Intrinsics shared by both models. Subclasses implement the normalized-plane mapping."""

    model: str

    def __init__(self, width: int, height: int, fx: float, fy: float, cx: float, cy: float, prefix: str) -> None:
        self.width = _positive_int(width, f"{prefix}.width")
        self.height = _positive_int(height, f"{prefix}.height")
        self.fx = _positive_number(fx, f"{prefix}.fx")
        self.fy = _positive_number(fy, f"{prefix}.fy")
        self.cx = _finite_number(cx, f"{prefix}.cx")
        self.cy = _finite_number(cy, f"{prefix}.cy")

    @property
    def K(self) -> F64:
        """(3, 3) float64 intrinsic matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], px."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def _to_normalized(self, uv: F64) -> tuple[F64, F64]:
        return (uv[:, 0] - self.cx) / self.fx, (uv[:, 1] - self.cy) / self.fy

    def _to_pixels(self, x: F64, y: F64) -> F64:
        return np.stack([self.fx * x + self.cx, self.fy * y + self.cy], axis=1)

    def in_image(self, uv_px: F64, margin_px: float = 0.0) -> NDArray[np.bool_]:
        """uv_px: (N, 2) raw-image px -> (N,) bool: margin <= u < width - margin and the same for v.

        NaN coordinates are outside. A single (2,) point gives a 0-d bool array.
        """
        uv, single = as_points(uv_px, 2, "uv_px")
        m = float(margin_px)
        with np.errstate(invalid="ignore"):
            ok = (uv[:, 0] >= m) & (uv[:, 0] < self.width - m) & (uv[:, 1] >= m) & (uv[:, 1] < self.height - m)
        return ok[0] if single else ok

    def _intrinsics_dict(self) -> dict[str, Any]:
        return {
            "model": self.model,
            "width": self.width,
            "height": self.height,
            "fx": self.fx,
            "fy": self.fy,
            "cx": self.cx,
            "cy": self.cy,
        }


class PinholeCamera(_CameraBase):
    """Pinhole camera with OpenCV's radial-tangential distortion (k1, k2, p1, p2, k3).

    With normalized coordinates x = X/Z, y = Y/Z and r^2 = x^2 + y^2 the raw pixel is
    u = fx * x_d + cx, v = fy * y_d + cy where
    x_d = x (1 + k1 r^2 + k2 r^4 + k3 r^6) + 2 p1 x y + p2 (r^2 + 2 x^2),
    y_d = y (1 + k1 r^2 + k2 r^4 + k3 r^6) + p1 (r^2 + 2 y^2) + 2 p2 x y.

    Attributes: model = "pinhole", width/height (px), fx/fy/cx/cy (px), dist: (5,) float64 (k1, k2, p1, p2, k3).
    ``r_max``: normalized radius where the radial polynomial folds back (inf if it never does on r > 0);
    points beyond it give NaN.
    """

    model = "pinhole"
    #: ((intrinsics key), image_bounds()) of the last call: see ``image_bounds``.
    _image_bounds_cache: tuple[tuple[Any, ...], tuple[float, float, float, float]] | None = None
    #: The pipeline matches and projects in the undistorted pinhole image (ORB-SLAM2/3 undistort keypoints).
    image_undistorted = True

    def __init__(
        self,
        width: int,
        height: int,
        fx: float,
        fy: float,
        cx: float,
        cy: float,
        dist: Sequence[float] = (),
    ) -> None:
        super().__init__(width, height, fx, fy, cx, cy, "camera")
        d = _coefficients(dist, "camera.dist", (0, 4, 5))
        self.dist: NDArray[np.float64] = np.zeros(5)
        self.dist[: d.size] = d
        self.dist.setflags(write=False)
        k1, k2, _, _, k3 = self.dist
        # d(r (1 + k1 r^2 + k2 r^4 + k3 r^6))/dr = 1 + 3 k1 r^2 + 5 k2 r^4 + 7 k3 r^6, in u = r^2.
        self.r_max = math.sqrt(_first_positive_root([1.0, 3 * k1, 5 * k2, 7 * k3]))

    @property
    def is_distorted(self) -> bool:
        """True when any distortion coefficient is non-zero."""
        return bool(np.any(self.dist != 0.0))

    def __repr__(self) -> str:
        return (
            f"PinholeCamera(width={self.width}, height={self.height}, fx={self.fx}, fy={self.fy}, "
            f"cx={self.cx}, cy={self.cy}, dist={self.dist.tolist()})"
        )

    # -- normalized-plane distortion

    def _distort(self, x: F64, y: F64) -> tuple[F64, F64]:
        k1, k2, p1, p2, k3 = self.dist
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        valid = r2 < self.r_max**2
        return np.where(valid, xd, np.nan), np.where(valid, yd, np.nan)

    def _undistort(self, xd: F64, yd: F64) -> tuple[F64, F64]:
        """Invert the distortion by Newton's method on the 2x2 system, starting from the distorted point."""
        if not self.is_distorted:
            return xd.copy(), yd.copy()
        k1, k2, p1, p2, k3 = (float(c) for c in self.dist)
        x, y = xd.copy(), yd.copy()
        finite = np.isfinite(xd) & np.isfinite(yd)
        x[~finite] = 0.0
        y[~finite] = 0.0
        _newton_undistort(
            np.ascontiguousarray(xd, dtype=np.float64),
            np.ascontiguousarray(yd, dtype=np.float64),
            x,
            y,
            k1,
            k2,
            p1,
            p2,
            k3,
            _MAX_NEWTON_ITERS,
        )
        # Keep only true inverses inside the one-to-one region of the model.
        rx, ry = self._distort(x, y)
        err_px = np.hypot((rx - xd) * self.fx, (ry - yd) * self.fy)
        with np.errstate(invalid="ignore"):
            ok = finite & (err_px <= _RESIDUAL_TOL_PX)
        return np.where(ok, x, np.nan), np.where(ok, y, np.nan)

    # -- Camera protocol

    def project(self, xyz_c: F64) -> F64:
        """xyz_c: (N, 3) m in the camera frame -> (N, 2) float64 raw-image px (NaN where z <= 0 or beyond
        the distortion's valid radius)."""
        xyz, single = as_points(xyz_c, 3, "xyz_c")
        z = xyz[:, 2]
        with np.errstate(invalid="ignore", divide="ignore"):
            zs = np.where(z > 0, z, np.nan)
            x, y = xyz[:, 0] / zs, xyz[:, 1] / zs
        xd, yd = self._distort(x, y)
        return _finish(self._to_pixels(xd, yd), single)

    def unproject(self, uv_px: F64) -> F64:
        """uv_px: (N, 2) raw-image px -> (N, 3) float64 unit bearing vectors in the camera frame (z > 0)."""
        uv, single = as_points(uv_px, 2, "uv_px")
        x, y = self._undistort(*self._to_normalized(uv))
        return _finish(_unit(np.stack([x, y, np.ones_like(x)], axis=1)), single)

    def undistort_points(self, uv_px: F64) -> F64:
        """uv_px: (N, 2) raw-image px -> (N, 2) float64 px in the ideal pinhole image with the same K."""
        uv, single = as_points(uv_px, 2, "uv_px")
        x, y = self._undistort(*self._to_normalized(uv))
        return _finish(self._to_pixels(x, y), single)

    def distort_points(self, uv_undist_px: F64) -> F64:
        """uv_undist_px: (N, 2) ideal-pinhole px -> (N, 2) float64 raw-image px."""
        uv, single = as_points(uv_undist_px, 2, "uv_undist_px")
        xd, yd = self._distort(*self._to_normalized(uv))
        return _finish(self._to_pixels(xd, yd), single)

    def to_dict(self) -> dict[str, Any]:
        """Plain dict (model, width, height, fx, fy, cx, cy, dist as 5 floats) for camera_from_config."""
        return {**self._intrinsics_dict(), "dist": [float(c) for c in self.dist]}

    # -- the pipeline's image: the ideal pinhole image (undistorted keypoints, as ORB-SLAM2/3 do)

    def image_bounds(self) -> tuple[float, float, float, float]:
        """(min_u, max_u, min_v, max_v) px of the pipeline's image: the undistorted corners of the raw image
        (ORB-SLAM ComputeImageBounds, once per camera); the raw image's bounds when a corner has no undistortion.

        Computed once per set of intrinsics: every frame asks (the Newton undistortion of the corners cost ~4 ms
        a frame), and the key makes a changed attribute recompute rather than return stale bounds."""
        key = (self.width, self.height, self.fx, self.fy, self.cx, self.cy, self.dist.tobytes())
        cached = self._image_bounds_cache
        if cached is not None and cached[0] == key:
            return cached[1]
        bounds = self._undistorted_corner_bounds()
        self._image_bounds_cache = (key, bounds)
        return bounds

    def _undistorted_corner_bounds(self) -> tuple[float, float, float, float]:
        w, h = self.width, self.height
        corners = np.array([[0.0, 0.0], [w, 0.0], [0.0, h], [w, h]])
        und = self.undistort_points(corners)
        if not np.all(np.isfinite(und)):
            return 0.0, float(w), 0.0, float(h)
        return (
            float(min(und[0, 0], und[2, 0])),
            float(max(und[1, 0], und[3, 0])),
            float(min(und[0, 1], und[1, 1])),
            float(max(und[2, 1], und[3, 1])),
        )

    def project_image(self, xyz_c: F64) -> tuple[F64, NDArray[np.bool_]]:
        """xyz_c: (N, 3) m camera frame -> (uv (N, 2) px in the undistorted pinhole image, valid (N,) bool:
        z > 0 and a finite pixel). u = fx x / z + cx (evaluated in this order: the pipeline's results depend
        on it bit for bit)."""
        z = xyz_c[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = self.fx * xyz_c[:, 0] / z + self.cx
            v = self.fy * xyz_c[:, 1] / z + self.cy
        uv = np.stack([u, v], axis=1)
        valid = (z > 0) & np.isfinite(u) & np.isfinite(v)
        return uv, valid

    def unproject_image(self, uv_px: F64) -> F64:
        """uv_px: (N, 2) px in the undistorted pinhole image -> (N, 3) float64 unit bearings (z > 0)."""
        uv = np.asarray(uv_px, dtype=np.float64).reshape(-1, 2)
        x, y = self._to_normalized(uv)
        return _unit(np.stack([x, y, np.ones_like(x)], axis=1))

    def project_image_jacobian(self, xyz_c: F64) -> F64:
        """xyz_c: (N, 3) m -> (N, 2, 3) d uv / d xyz_c of ``project_image`` (px/m): rows (fx/z, 0, -fx x/z^2)
        and (0, fy/z, -fy y/z^2). NaN where z = 0."""
        x, y, z = np.asarray(xyz_c, dtype=np.float64).reshape(-1, 3).T
        with np.errstate(divide="ignore", invalid="ignore"):
            iz = 1.0 / z
            J = np.zeros((x.size, 2, 3))
            J[:, 0, 0] = self.fx * iz
            J[:, 0, 2] = -self.fx * x * iz * iz
            J[:, 1, 1] = self.fy * iz
            J[:, 1, 2] = -self.fy * y * iz * iz
        return J


class KannalaBrandtCamera(_CameraBase):
    """Equidistant fisheye model of Kannala-Brandt (ORB-SLAM3's KannalaBrandt8, OpenCV's cv2.fisheye).

    For a point at angle theta = atan2(sqrt(X^2 + Y^2), Z) from the optical axis,
    theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8) and the raw pixel is
    u = fx theta_d X / r + cx, v = fy theta_d Y / r + cy with r = sqrt(X^2 + Y^2). Points behind the camera
    (z <= 0) are imaged as long as theta is below ``theta_max``, where theta_d(theta) stops increasing
    (capped at pi).

    Attributes: model = "kannala_brandt", width/height/fx/fy/cx/cy, k: (4,) float64, theta_max (rad).
    """

    model = "kannala_brandt"
    #: The pipeline matches and projects in the raw image (ORB-SLAM3 keeps fisheye keypoints distorted).
    image_undistorted = False

    def __init__(
        self,
        width: int,
        height: int,
        fx: float,
        fy: float,
        cx: float,
        cy: float,
        k: Sequence[float],
    ) -> None:
        super().__init__(width, height, fx, fy, cx, cy, "camera")
        self.k: NDArray[np.float64] = _coefficients(k, "camera.k", (4,))
        self.k.setflags(write=False)
        k1, k2, k3, k4 = self.k
        # d theta_d / d theta = 1 + 3 k1 t^2 + 5 k2 t^4 + 7 k3 t^6 + 9 k4 t^8, in u = t^2.
        self.theta_max = min(math.pi, math.sqrt(_first_positive_root([1.0, 3 * k1, 5 * k2, 7 * k3, 9 * k4])))

    @property
    def dist(self) -> NDArray[np.float64]:
        """(4,) the fisheye coefficients k1..k4 (same as ``k``; the name OpenCV uses for ``D``)."""
        return self.k

    @property
    def is_distorted(self) -> bool:
        """Always True: the equidistant projection differs from a pinhole even with k = 0."""
        return True

    def __repr__(self) -> str:
        return (
            f"KannalaBrandtCamera(width={self.width}, height={self.height}, fx={self.fx}, fy={self.fy}, "
            f"cx={self.cx}, cy={self.cy}, k={self.k.tolist()})"
        )

    def _theta_d(self, theta: F64) -> F64:
        k1, k2, k3, k4 = self.k
        t2 = theta * theta
        out: F64 = theta * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
        return out

    def _theta_from_theta_d(self, theta_d: F64) -> F64:
        """Invert theta_d(theta) on [0, theta_max] by Newton's method safeguarded with bisection."""
        k1, k2, k3, k4 = self.k
        lo = np.zeros_like(theta_d)
        hi = np.full_like(theta_d, self.theta_max)
        inside = theta_d <= self._theta_d(hi)
        theta = np.clip(theta_d, 0.0, self.theta_max)
        for _ in range(_MAX_NEWTON_ITERS):
            t2 = theta * theta
            f = theta * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))) - theta_d
            df = 1.0 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))
            # Maintain the bracket (theta_d is increasing on [0, theta_max]).
            lo = np.where(f < 0, theta, lo)
            hi = np.where(f > 0, theta, hi)
            with np.errstate(invalid="ignore", divide="ignore"):
                step = f / df
            new = theta - step
            bad = ~np.isfinite(new) | (new < lo) | (new > hi)
            new = np.where(bad, 0.5 * (lo + hi), new)
            done = np.abs(new - theta) <= 1e-15 * (1.0 + theta)
            theta = new
            if np.all(done | ~np.isfinite(theta_d)):
                break
        with np.errstate(invalid="ignore"):
            ok = inside & (np.abs(self._theta_d(theta) - theta_d) * max(self.fx, self.fy) <= _RESIDUAL_TOL_PX)
        return np.where(ok, theta, np.nan)

    def _project_rays(self, xyz: F64) -> F64:
        r = np.hypot(xyz[:, 0], xyz[:, 1])
        theta = np.arctan2(r, xyz[:, 2])
        theta_d = np.where(theta <= self.theta_max, self._theta_d(theta), np.nan)
        with np.errstate(invalid="ignore", divide="ignore"):
            # On the optical axis (r = 0) the pixel is the principal point, whatever theta_d / r tends to.
            scale = np.where(r > 0, theta_d / np.where(r > 0, r, 1.0), 0.0)
        scale[(r == 0) & ~(xyz[:, 2] > 0)] = np.nan  # the origin, or straight behind: no direction
        return self._to_pixels(scale * xyz[:, 0], scale * xyz[:, 1])

    def project(self, xyz_c: F64) -> F64:
        """xyz_c: (N, 3) m in the camera frame -> (N, 2) float64 raw-image px (NaN beyond theta_max)."""
        xyz, single = as_points(xyz_c, 3, "xyz_c")
        return _finish(self._project_rays(xyz), single)

    def unproject(self, uv_px: F64) -> F64:
        """uv_px: (N, 2) raw-image px -> (N, 3) float64 unit bearing vectors (z may be <= 0 for wide lenses)."""
        uv, single = as_points(uv_px, 2, "uv_px")
        mx, my = self._to_normalized(uv)
        theta_d = np.hypot(mx, my)
        theta = self._theta_from_theta_d(theta_d)
        with np.errstate(invalid="ignore", divide="ignore"):
            s = np.where(theta_d > 0, np.sin(theta) / np.where(theta_d > 0, theta_d, 1.0), 1.0)
        bearings = np.stack([s * mx, s * my, np.cos(theta)], axis=1)
        return _finish(bearings, single)

    def undistort_points(self, uv_px: F64) -> F64:
        """uv_px: (N, 2) raw-image px -> (N, 2) float64 px in the ideal pinhole image with the same K
        (NaN for rays with z <= 0, which a pinhole cannot image)."""
        uv, single = as_points(uv_px, 2, "uv_px")
        b = self.unproject(uv)
        with np.errstate(invalid="ignore", divide="ignore"):
            z = np.where(b[:, 2] > 0, b[:, 2], np.nan)
            out = self._to_pixels(b[:, 0] / z, b[:, 1] / z)
        return _finish(out, single)

    def distort_points(self, uv_undist_px: F64) -> F64:
        """uv_undist_px: (N, 2) ideal-pinhole px (same K) -> (N, 2) float64 raw-image px."""
        uv, single = as_points(uv_undist_px, 2, "uv_undist_px")
        x, y = self._to_normalized(uv)
        return _finish(self._project_rays(np.stack([x, y, np.ones_like(x)], axis=1)), single)

    def to_dict(self) -> dict[str, Any]:
        """Plain dict (model, width, height, fx, fy, cx, cy, k as 4 floats) for camera_from_config."""
        return {**self._intrinsics_dict(), "k": [float(c) for c in self.k]}

    # -- the pipeline's image: the raw image itself (ORB-SLAM3 matches and projects fisheye keypoints unrectified)

    def image_bounds(self) -> tuple[float, float, float, float]:
        """(min_u, max_u, min_v, max_v) px of the pipeline's image: the raw image (0, width, 0, height)."""
        return 0.0, float(self.width), 0.0, float(self.height)

    def project_image(self, xyz_c: F64) -> tuple[F64, NDArray[np.bool_]]:
        """xyz_c: (N, 3) m camera frame -> (uv (N, 2) raw-image px, valid (N,) bool: z > 0 (ORB-SLAM3's
        isInFrustum requires positive depth for every camera), theta <= theta_max and a finite pixel)."""
        xyz = np.asarray(xyz_c, dtype=np.float64).reshape(-1, 3)
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = self._project_rays(xyz)
        valid = (xyz[:, 2] > 0) & np.isfinite(uv[:, 0]) & np.isfinite(uv[:, 1])
        return uv, valid

    def unproject_image(self, uv_px: F64) -> F64:
        """uv_px: (N, 2) raw-image px -> (N, 3) float64 unit bearings (the same as ``unproject``)."""
        return self.unproject(np.asarray(uv_px, dtype=np.float64).reshape(-1, 2))

    def project_image_jacobian(self, xyz_c: F64) -> F64:
        """xyz_c: (N, 3) m -> (N, 2, 3) d uv / d xyz_c of ``project_image`` (px/m).

        With r = |(x, y)|, R^2 = r^2 + z^2, theta = atan2(r, z), s = theta_d / r and theta_d' = d theta_d / d theta:
        d s / d(x, y) = (x, y) A with A = theta_d' z / (r^2 R^2) - theta_d / r^3, d s / d z = -theta_d' / R^2, so
        d u / d p = fx (s e_x + x d s / d p) and d v / d p = fy (s e_y + y d s / d p). On the optical axis
        (r -> 0) s -> 1 / z and the x A, y A terms vanish: the pinhole Jacobian there.
        """
        x, y, z = np.asarray(xyz_c, dtype=np.float64).reshape(-1, 3).T
        k1, k2, k3, k4 = self.k
        r2 = x * x + y * y
        r = np.sqrt(r2)
        R2 = r2 + z * z
        theta = np.arctan2(r, z)
        t2 = theta * theta
        theta_d = theta * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
        dtheta_d = 1.0 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))
        on_axis = r <= 1e-12 * np.maximum(np.abs(z), 1e-300)
        with np.errstate(divide="ignore", invalid="ignore"):
            rs = np.where(on_axis, 1.0, r)
            s = np.where(on_axis, 1.0 / z, theta_d / rs)
            A = np.where(on_axis, 0.0, dtheta_d * z / (rs * rs * R2) - theta_d / (rs * rs * rs))
            ds_dz = -dtheta_d / R2
        J = np.empty((x.size, 2, 3))
        J[:, 0, 0] = self.fx * (s + x * x * A)
        J[:, 0, 1] = self.fx * x * y * A
        J[:, 0, 2] = self.fx * x * ds_dz
        J[:, 1, 0] = self.fy * x * y * A
        J[:, 1, 1] = self.fy * (s + y * y * A)
        J[:, 1, 2] = self.fy * y * ds_dz
        return J


_INTRINSIC_KEYS = ("width", "height", "fx", "fy", "cx", "cy")
_MODEL_KEYS = {"pinhole": ("dist",), "kannala_brandt": ("k",)}


def camera_from_config(cfg: Mapping[str, Any], key: str = "camera") -> PinholeCamera | KannalaBrandtCamera:
    """Build a camera from a config mapping (a dict or an OmegaConf DictConfig).

    Keys: model ("pinhole", the default, or "kannala_brandt"), width, height (px, positive integers),
    fx, fy (px, positive), cx, cy (px), and dist (pinhole: 0, 4 or 5 coefficients k1, k2, p1, p2[, k3];
    optional) or k (fisheye: 4 coefficients k1..k4; required). Unknown keys are rejected so that a typo
    (e.g. ``k1`` for a pinhole) is not silently ignored. ``key`` is the config path used in messages,
    e.g. "camera.fx: expected a positive number, got -3".
    """
    if not isinstance(cfg, Mapping):
        raise ConfigError(f"{key}: expected a mapping of camera parameters, got {type(cfg).__name__}")
    model = cfg.get("model", "pinhole")
    if model not in _MODEL_KEYS:
        raise ConfigError(f"{key}.model: expected 'pinhole' or 'kannala_brandt', got {model!r}")
    allowed = {"model", *_INTRINSIC_KEYS, *_MODEL_KEYS[model]}
    unknown = sorted(str(k) for k in cfg if k not in allowed)
    if unknown:
        raise ConfigError(f"{key}.{unknown[0]}: unknown key for a {model} camera; expected keys {sorted(allowed)}")
    for name in _INTRINSIC_KEYS:
        if name not in cfg:
            raise ConfigError(f"{key}.{name}: missing (required for a {model} camera)")
    width = _positive_int(cfg["width"], f"{key}.width")
    height = _positive_int(cfg["height"], f"{key}.height")
    fx = _positive_number(cfg["fx"], f"{key}.fx")
    fy = _positive_number(cfg["fy"], f"{key}.fy")
    cx = _finite_number(cfg["cx"], f"{key}.cx")
    cy = _finite_number(cfg["cy"], f"{key}.cy")
    if model == "pinhole":
        dist = _coefficients(cfg.get("dist", ()), f"{key}.dist", (0, 4, 5))
        return PinholeCamera(width, height, fx, fy, cx, cy, dist=list(dist))
    if "k" not in cfg:
        raise ConfigError(f"{key}.k: missing (4 coefficients k1..k4 are required for a kannala_brandt camera)")
    k = _coefficients(cfg["k"], f"{key}.k", (4,))
    return KannalaBrandtCamera(width, height, fx, fy, cx, cy, k=list(k))
