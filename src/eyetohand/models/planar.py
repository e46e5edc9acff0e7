"""The planar matrix models: one 3×3 matrix from (normalised) pixels to the robot's plane.

``Homography`` is the general one (8 free elements, H[2, 2] = 1); ``Affine`` is the same map with its
last row fixed at (0, 0, 1) — fewer free coefficients, the same code. Both keep their parameters in
Hartley-normalised coordinates (well conditioned for the solvers) and give the matrix in pixels → mm
as ``matrix_image_to_robot``. Subclasses that correct the pixels first (a lens) override
``_ideal_px`` / ``_distorted_px``.
"""

from __future__ import annotations

import math
from abc import abstractmethod
from types import MappingProxyType
from typing import ClassVar

import numpy as np

from eyetohand.core import DegenerateError
from eyetohand.geometry import apply_h, hartley
from eyetohand.models.base import (
    CV_CHUNK,
    CV_MIN_POINTS,
    MAP_CHUNK,
    HeightRule,
    Model,
    as_uv,
    check_enough,
    check_not_collinear,
    check_single_height,
    one_point,
    opencv,
    opencv_xy_into,
    plane_constants,
    refuse_non_finite,
    rows_kernel,
)

PLANAR_CONSTANTS = MappingProxyType({"T_uv": (3, 3), "T_xy": (3, 3), "plane_z_mm": ()})
PLANE_SLOPE = MappingProxyType({"plane_slope": (2,)})  # optional: absent for a level plane


def planar_setup(name: str, min_pairs: int, uv_px, xyz_mm):
    """Validate planar pairs and return ``(uv, xyz, plane, T_uv, T_xy, uv_n, xy_n)``: ``plane`` the
    height constants of the pairs' plane (``plane_constants``; refused when not one height)."""
    uv = np.asarray(uv_px, dtype=float)
    xyz = np.asarray(xyz_mm, dtype=float)
    check_enough(name, min_pairs, len(uv))
    check_not_collinear(name, uv, xyz[:, :2])
    plane = plane_constants(check_single_height(name, xyz))
    T_uv, uv_n = hartley(uv)
    T_xy, xy_n = hartley(xyz[:, :2])
    return uv, xyz, plane, T_uv, T_xy, uv_n, xy_n


# the NaN this machine's floating point gives for an invalid operation (0/0, inf - inf): its sign bit
# differs from math.nan's on x86-64, and the many-point paths give this one
_INVALID_NAN = math.inf - math.inf


def ieee_over_zero(a: float, zero: float) -> float:
    """``a / zero`` for ``zero`` = ±0.0 as IEEE 754 (and NumPy, and the compiled loop) divide, bit for
    bit: ±inf signed by both operands, a NaN ``a`` itself, 0/0 the invalid operation's NaN — where
    Python's float division raises ZeroDivisionError."""
    if a != a:
        return a
    if a == 0.0:
        return _INVALID_NAN
    return math.copysign(math.inf, a) * math.copysign(1.0, zero)


def to_robot(xy_n: np.ndarray, Tinv_xy: np.ndarray, z_mm: np.ndarray) -> np.ndarray:
    """Normalised plane points (P, N, 2) → robot (P, N, 3), z taken from ``z_mm`` (N,)."""
    xy = xy_n * Tinv_xy[0, 0] + Tinv_xy[:2, 2]
    z = np.broadcast_to(z_mm, xy.shape[:2])
    return np.concatenate([xy, z[..., None]], axis=-1)


class PlanarMatrixModel(Model):
    """(x, y, 1) ~ T_xy⁻¹ · M(params) · T_uv · (u', v', 1), with (u', v') = ``_ideal_px(u, v)``."""

    height_rule: ClassVar[HeightRule] = HeightRule.PLANE
    constant_shapes = PLANAR_CONSTANTS
    optional_constant_shapes = PLANE_SLOPE

    def _prepare(self) -> None:
        self._T_uv = np.asarray(self.constants["T_uv"], float)
        self._Tinv_xy = np.linalg.inv(np.asarray(self.constants["T_xy"], float))
        # what the parameters fix: the px → mm matrix, as floats for one point and for columns
        H = self._Tinv_xy @ self.batch_matrices(self.params[None])[0] @ self._T_uv
        if not (np.isfinite(H).all() and abs(H[2, 2]) > 1e-300):
            raise DegenerateError(
                f"model '{self.name}': degenerate matrix (it maps pixels to the plane at infinity)"
            )
        self._H_px = H / H[2, 2]
        self._h = tuple(self._H_px.ravel().tolist())
        self._h_flat = np.ascontiguousarray(self._H_px.ravel())
        self._M = tuple(self.batch_matrices(self.params[None])[0].ravel().tolist())
        self._affine = self._h[6] == 0.0 and self._h[7] == 0.0
        self._z0 = float(self.constants["plane_z_mm"])
        self._slope = self.plane_slope
        self._tilted = self._slope != (0.0, 0.0)

    @staticmethod
    @abstractmethod
    def batch_matrices(params) -> np.ndarray:
        """(P, 3, 3) normalised matrices from (P, D) parameter rows."""

    def _ideal_px(self, uv_px: np.ndarray) -> np.ndarray:
        """Pixels as the matrix sees them (a lens model undistorts here)."""
        return uv_px

    def _distorted_px(self, uv_px: np.ndarray) -> np.ndarray:
        """The inverse of ``_ideal_px``."""
        return uv_px

    def batch_image_to_robot(self, params, uv_px, z_mm):
        M = self.batch_matrices(params)
        pts = apply_h(self._T_uv, self._ideal_px(np.asarray(uv_px, float)))
        num = np.einsum("pij,nj->pni", M[:, :, :2], pts) + M[:, None, :, 2]
        return to_robot(num[..., :2] / num[..., 2:3], self._Tinv_xy, z_mm)

    def batch_map_and_jacobian(self, params, uv_px, z_mm):
        """(P, N, 3) mapped pairs and (P, N, 3, D) d(x, y, z)/d(params) in closed form (see
        :meth:`params_jacobian`), elementwise over (P, N): no (P, 2D, N) difference rows."""
        P = np.asarray(params, float).reshape(-1, self.n_params)
        D = self.n_params
        pts = apply_h(self._T_uv, self._ideal_px(np.asarray(uv_px, float)))
        p0, p1 = pts[:, 0], pts[:, 1]
        M = self.batch_matrices(P).reshape(len(P), 9)
        m = [M[:, k, None] for k in range(9)]
        nx = m[0] * p0 + m[1] * p1 + m[2]
        ny = m[3] * p0 + m[4] * p1 + m[5]
        w = m[6] * p0 + m[7] * p1 + m[8]
        s = self._Tinv_xy[0, 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            g = s / w
            xn, yn = nx / w, ny / w
        out = np.empty((len(P), len(p0), 3))
        out[..., 0] = s * xn + self._Tinv_xy[0, 2]
        out[..., 1] = s * yn + self._Tinv_xy[1, 2]
        out[..., 2] = z_mm
        J = np.zeros((len(P), len(p0), 3, D))
        gx, gy = g * p0, g * p1
        J[..., 0, 0], J[..., 0, 1], J[..., 0, 2] = gx, gy, g
        J[..., 1, 3], J[..., 1, 4], J[..., 1, 5] = gx, gy, g
        if D == 8:
            J[..., 0, 6], J[..., 0, 7] = -gx * xn, -gy * xn
            J[..., 1, 6], J[..., 1, 7] = -gx * yn, -gy * yn
        return out, J

    @property
    def matrix_image_to_robot(self) -> np.ndarray:
        """3×3 matrix mapping (u', v', 1) px to (x, y, 1) mm (up to scale; [2, 2] = 1)."""
        return self._H_px.copy()

    def jacobian_det_range(self, polygon_px: np.ndarray) -> tuple[float, float] | None:
        """det d(x, y)/d(u, v) = det H / w³, w = h₆u + h₇v + 1 affine in the pixel, so over a convex
        polygon w ranges between its values at the vertices, and the answer's x, y (ratios of affine
        functions to w, which keeps its sign) take their extremes there: finite at the vertices, finite
        throughout. None where w reaches 0 (the horizon), the answer at a vertex is not finite, or a
        lens model bends the pixels first (its form gives no such bound here)."""
        if type(self)._ideal_px is not PlanarMatrixModel._ideal_px:
            return None
        H = self._H_px
        p = np.asarray(polygon_px, float).reshape(-1, 2)
        w = H[2, 0] * p[:, 0] + H[2, 1] * p[:, 1] + H[2, 2]
        lo, hi = float(w.min()), float(w.max())
        if not (lo > 0.0 or hi < 0.0) or not math.isfinite(lo * hi):
            return None
        if not np.isfinite(self.image_to_robot(p)).all():
            return None
        d = [float(np.linalg.det(H)) / lo**3, float(np.linalg.det(H)) / hi**3]
        return min(d), max(d)

    def _ideal_one(self, u: float, v: float) -> tuple[float, float]:
        """``_ideal_px`` of one point, on plain floats (NaN where the lens cannot be inverted)."""
        return u, v

    def image_to_robot(self, uv_px, z_mm=None) -> np.ndarray:
        """As :meth:`Model.image_to_robot`; with no ``z_mm``, z is the calibration plane's at the
        mapped x, y (z = a·x + b·y + c: a tilted plane's height depends on where)."""
        out = self._map_on_plane(uv_px, z_mm)
        if z_mm is None and self._tilted:
            a, b = self._slope
            out[:, 2] = a * out[:, 0] + b * out[:, 1] + self._z0
        return out

    def _map_on_plane(self, uv_px, z_mm=None) -> np.ndarray:
        """As :meth:`Model.image_to_robot`, through the precomputed px → mm matrix: one point on plain
        floats; many, without a lens, in one pass of the compiled loop (``rows_kernel``), else — and
        with a lens — elementwise in cache-sized chunks (no BLAS, no (P, N, ·) temporaries). Equal to
        ``batch_image_to_robot`` to rounding (tests/test_speed_paths.py)."""
        pt = one_point(uv_px)
        if pt is not None:
            if z_mm is None:
                z = self._z0
            else:
                z = self._z_for(1, z_mm)[0]
            u, v = self._ideal_one(*pt)
            h0, h1, h2, h3, h4, h5, h6, h7, h8 = self._h
            w = h6 * u + h7 * v + h8
            x, y = h0 * u + h1 * v + h2, h3 * u + h4 * v + h5
            if w == 0.0:  # on the horizon: Python raises where the many-point paths give IEEE's ±inf/NaN
                return np.array([[ieee_over_zero(x, w), ieee_over_zero(y, w), z]])
            return np.array([[x / w, y / w, z]])
        uv = as_uv(uv_px, check_finite=False)
        if type(self)._ideal_px is PlanarMatrixModel._ideal_px:  # no lens: one matrix on the pixels
            zq = self._z_for(1, z_mm)[0] if z_mm is None or np.ndim(z_mm) == 0 else self._z_for(len(uv), z_mm)
            rows = rows_kernel()
            if rows is not None:  # one compiled pass, equal to the chunks below bit for bit
                out = np.empty((len(uv), 3))
                zc = float(zq) if np.ndim(zq) == 0 else np.ascontiguousarray(zq)
                if not rows.planar_rows(np.ascontiguousarray(uv), self._h_flat, not self._affine, zc, out):
                    refuse_non_finite(uv)
                return out
            if len(uv) >= CV_MIN_POINTS:
                fast = self._map_opencv(uv, zq)
                if fast is not None:
                    return fast
        refuse_non_finite(uv)
        zs = self._z_for(len(uv), z_mm)
        out = np.empty((len(uv), 3))
        for s in range(0, len(uv), MAP_CHUNK):
            self._map_chunk(self._ideal_px(uv[s : s + MAP_CHUNK]), out[s : s + MAP_CHUNK, :2])
        out[:, 2] = zs
        return out

    def params_jacobian(self, uv_px, z_mm) -> np.ndarray:
        """(N, 2, D) d(x, y)/d(params) in closed form: the parameters are the first D elements of the
        normalised matrix M (row-major, M[2, 2] = 1), (x_n, y_n) = (M p)[:2] / (M p)[2] with p the
        normalised ideal pixel, and (x, y) = s (x_n, y_n) + c."""
        uv = np.asarray(uv_px, float).reshape(-1, 2)
        if len(uv) == 1:
            return self._params_jacobian_one(*self._ideal_one(float(uv[0, 0]), float(uv[0, 1])))
        pts = apply_h(self._T_uv, self._ideal_px(uv))
        M = self.batch_matrices(self.params[None])[0]
        num = pts @ M[:, :2].T + M[:, 2]
        w = num[:, 2]
        s = self._Tinv_xy[0, 0]
        D = self.n_params
        J = np.zeros((len(uv), 2, D))
        g = s / w
        for j, pj in enumerate((pts[:, 0], pts[:, 1], 1.0)):
            J[:, 0, j] = g * pj
            J[:, 1, 3 + j] = g * pj
        if D == 8:
            for j in range(2):
                J[:, 0, 6 + j] = -g * num[:, 0] / w * pts[:, j]
                J[:, 1, 6 + j] = -g * num[:, 1] / w * pts[:, j]
        return J

    def _params_jacobian_one(self, u: float, v: float) -> np.ndarray:
        """``params_jacobian`` of one ideal pixel, on plain floats."""
        T = self._T_uv
        p0 = T[0, 0] * u + T[0, 1] * v + T[0, 2]
        p1 = T[1, 0] * u + T[1, 1] * v + T[1, 2]
        m = self._M
        w = m[6] * p0 + m[7] * p1 + m[8]
        g = self._Tinv_xy[0, 0] / w
        gx, gy = g * p0, g * p1
        if self.n_params == 6:
            return np.array([[[gx, gy, g, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, gx, gy, g]]])
        xn = (m[0] * p0 + m[1] * p1 + m[2]) / w
        yn = (m[3] * p0 + m[4] * p1 + m[5]) / w
        return np.array(
            [[[gx, gy, g, 0.0, 0.0, 0.0, -gx * xn, -gy * xn], [0.0, 0.0, 0.0, gx, gy, g, -gx * yn, -gy * yn]]]
        )

    def _map_opencv(self, uv: np.ndarray, zs) -> np.ndarray | None:
        """Where the compiled loop was not built (``rows_kernel()`` is None): many pixels (no lens)
        through OpenCV's float64 2 → 2 ``transform`` with the precomputed
        px → mm matrix (``opencv_xy_into``: no BLAS, no 16 MB intermediates; a one-pass 2 → 3
        channel ``cv2.transform`` measured 2.3× slower). A homography takes two: its numerators
        and its w (in both channels), and ``cv2.divide`` — IEEE division, so a point on the horizon
        maps to ±inf as in the NumPy path (``perspectiveTransform`` writes (0, 0) there and needed a
        ``countNonZero`` pass and a re-map of those points); the three calls take about what
        ``perspectiveTransform`` does (1.6 against 1.5 ms per 10⁶, docs/performance.md). ``zs``: one
        height (a number) or (N,). None when OpenCV is not importable."""
        cv2 = opencv()
        if cv2 is None:
            return None
        out = np.empty((len(uv), 3))
        scalar = np.ndim(zs) == 0  # one height for all the points (the plane's, or one given)
        numerators = self._H_px[:2]
        if self._affine:

            def xy_into(src: np.ndarray, b: np.ndarray) -> None:
                cv2.transform(src, numerators, dst=b)

        else:
            w_rows = np.vstack([self._H_px[2], self._H_px[2]])
            wbuf = np.empty((min(CV_CHUNK, len(uv)), 1, 2))

            def xy_into(src: np.ndarray, b: np.ndarray) -> None:
                wb = wbuf[: len(b)]
                cv2.transform(src, numerators, dst=b)
                cv2.transform(src, w_rows, dst=wb)
                cv2.divide(b, wb, dst=b)

        def fill_z(s: int, e: int) -> None:
            out[s:e, 2] = zs if scalar else zs[s:e]

        opencv_xy_into(cv2, uv, out, xy_into, fill_z)
        return out

    def _map_chunk(self, uv: np.ndarray, xy: np.ndarray) -> None:
        """(n, 2) ideal px → ``xy`` (n, 2) mm in place, elementwise."""
        h0, h1, h2, h3, h4, h5, h6, h7, h8 = self._h
        u, v = uv[:, 0], uv[:, 1]
        x, y = xy[:, 0], xy[:, 1]
        t = np.multiply(v, h1)
        np.multiply(u, h0, out=x)
        x += t
        x += h2
        np.multiply(v, h4, out=t)
        np.multiply(u, h3, out=y)
        y += t
        y += h5
        if not self._affine:
            w = np.multiply(u, h6)
            np.multiply(v, h7, out=t)
            w += t
            w += h8
            with np.errstate(divide="ignore", invalid="ignore"):
                x /= w
                y /= w

    def robot_to_image(self, xyz_mm) -> np.ndarray:
        xyz = np.atleast_2d(np.asarray(xyz_mm, dtype=float))
        return self._distorted_px(apply_h(np.linalg.inv(self._H_px), xyz[:, :2]))
