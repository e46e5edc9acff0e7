"""Homography plus radial lens distortion: the paper's own remark that its linear model ignores the
lens, answered.

Mapping, image → robot: undistort the pixel (radial k1, k2 about the distortion centre c, in
f-normalised units as OpenCV), then a free homography H from ideal pixels to the robot's plane::

    n_d = (uv - c) / f,   n_d = n·(1 + k1 r² + k2 r⁴),   uv_ideal = c + f·n,   (x, y, 1) ~ H·(uv_ideal, 1)

Estimation follows what OpenCV's single-view ``calibrateCamera`` + ``findHomography`` does, because
with few points a physically constrained fit of the lens generalises better than a free one:

1. the lens: a camera with the principal point fixed at c, square pixels, no tangential terms —
   focal length f, k1, k2 and the plane's pose (9 unknowns) — fitted by Levenberg–Marquardt on the
   image-space reprojection error, started from the DLT homography's decomposition (f from Zhang's
   two constraints, or a default when the view is too straight-on to tell);
2. the plane: a homography from the undistorted pixels to the robot's (x, y), normalised DLT.
   The solvers (``lm``, the PSOs) refine its 8 elements on the robot-space residuals (eq. 16);
   f, k1, k2 stay as estimated in step 1 (``meta``).

Distortion centre c: the image centre ((W−1)/2, (H−1)/2) when the image size is known, otherwise the
centre of the training points' bounding box (``diagnostics["centre_source"]`` says which). Seen straight on,
f and the camera's distance cannot be told apart; the lens fit then settles on one of the equivalent
(f, k1, k2) and the mapping is the same.
"""

from __future__ import annotations

from types import MappingProxyType

import numpy as np

from ..lens import distort, matrix_to_rodrigues, rodrigues_to_matrix, undistort
from ..normalize import hartley
from .homography import Homography, dlt_homography
from .planar import PLANAR_CONSTANTS, planar_setup


def focal_from_homography(H_plane_to_image: np.ndarray, centre: np.ndarray) -> float | None:
    """Focal length (px) from a plane→image homography with known principal point and square
    pixels (Zhang's two constraints, least squares); None when the view is too straight-on."""
    T = np.array([[1, 0, -centre[0]], [0, 1, -centre[1]], [0, 0, 1.0]])
    H = T @ H_plane_to_image
    H = H / np.linalg.norm(H[:, 0])
    h1, h2 = H[:, 0], H[:, 1]
    A = np.array([h1[0] * h2[0] + h1[1] * h2[1], h1[0] ** 2 + h1[1] ** 2 - h2[0] ** 2 - h2[1] ** 2])
    B = np.array([h1[2] * h2[2], h1[2] ** 2 - h2[2] ** 2])
    denom = A @ A
    if denom < 1e-30 or np.linalg.norm(B) < 1e-9 * np.linalg.norm(A):
        return None
    a = -(A @ B) / denom  # 1 / f^2
    if not np.isfinite(a) or a <= 0:
        return None
    return float(1.0 / np.sqrt(a))


def pose_from_homography(H_plane_to_image: np.ndarray, centre: np.ndarray, f: float):
    """(rvec, tvec) of the plane in the camera from its homography and the intrinsics."""
    Kinv = np.array([[1 / f, 0, -centre[0] / f], [0, 1 / f, -centre[1] / f], [0, 0, 1.0]])
    G = Kinv @ H_plane_to_image
    lam = 2.0 / (np.linalg.norm(G[:, 0]) + np.linalg.norm(G[:, 1]))
    if G[2, 2] * lam < 0:
        lam = -lam
    r1, r2, t = lam * G[:, 0], lam * G[:, 1], lam * G[:, 2]
    U, _, Vt = np.linalg.svd(np.column_stack([r1, r2, np.cross(r1, r2)]))
    R = U @ Vt
    if np.linalg.det(R) < 0:
        R = U @ np.diag([1, 1, -1]) @ Vt
    return matrix_to_rodrigues(R), t


def project_plane(p: np.ndarray, xy_mm: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """Pixels of plane points (x, y, 0) for camera parameters p = (f, k1, k2, r(3), t(3))."""
    R = rodrigues_to_matrix(p[3:6])
    Xc = np.column_stack([xy_mm, np.zeros(len(xy_mm))]) @ R.T + p[6:9]
    n = Xc[:, :2] / Xc[:, 2:3]
    return centre + p[0] * distort(n, np.array([p[1], p[2], 0.0, 0.0]))


def fit_lens(uv_px, xy_mm, centre, f_default):
    """Single-view camera fit (f, k1, k2, pose) on image-space residuals; returns (params, rms_px)."""
    T_uv, uv_n = hartley(uv_px)
    T_xy, xy_n = hartley(xy_mm)
    Hn, _ = dlt_homography(xy_n, uv_n, "homography-radial")
    H = np.linalg.inv(T_uv) @ Hn @ T_xy
    f = focal_from_homography(H, centre)
    if f is None or not (0.1 * f_default < f < 10 * f_default):
        f = f_default
    rvec, tvec = pose_from_homography(H, centre, f)
    p0 = np.r_[f, 0.0, 0.0, rvec, tvec]
    from scipy.optimize import least_squares  # lazily: SciPy costs ~0.4 s of start-up

    sol = least_squares(
        lambda p: (project_plane(p, xy_mm, centre) - uv_px).ravel(), p0, method="lm", x_scale="jac"
    )
    rms = float(np.sqrt(np.mean(sol.fun**2) * 2))
    return sol.x, rms


class HomographyRadial(Homography):
    """The homography, seen through a radial lens: pixels are undistorted (f, k1, k2 about the
    distortion centre, fixed by the lens fit) before the same planar matrix map; the solvers refine
    the homography's 8 elements."""

    name = "homography-radial"
    n_params = 8  # the homography; f, k1, k2 are fixed by the lens fit
    unknowns = 10  # 8 + k1, k2 (f only sets k's units)
    min_pairs = 6
    summary = "10 unknowns: homography plus radial lens distortion k1, k2"
    loo_warm_start = False  # the lens (f, k1, k2) is re-fitted on each subset of pairs
    constant_shapes = MappingProxyType(
        {**PLANAR_CONSTANTS, "centre_px": (2,), "focal_px": (), "k1": (), "k2": ()}
    )

    @classmethod
    def from_pairs(cls, uv_px, xyz_mm, *, image_size=None) -> HomographyRadial:
        uv, xyz, z0, *_ = planar_setup(cls.name, cls.min_pairs, uv_px, xyz_mm)
        if image_size is not None:
            w, h = image_size
            centre = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
            f_default = 1.2 * max(w, h)
            source = "image-size"
        else:
            centre = 0.5 * (uv.min(axis=0) + uv.max(axis=0))
            f_default = 2.4 * float(np.abs(uv - centre).max())
            source = "points"
        lens, rms_px = fit_lens(uv, xyz[:, :2], centre, f_default)
        f, k1, k2 = (float(v) for v in lens[:3])
        ideal = undistort_px(uv, centre, f, k1, k2)
        T_uv, ideal_n = hartley(ideal)
        T_xy, xy_n = hartley(xyz[:, :2])
        H, cond = dlt_homography(ideal_n, xy_n, cls.name)
        constants = {
            "T_uv": T_uv.tolist(),
            "T_xy": T_xy.tolist(),
            "plane_z_mm": z0,
            "centre_px": centre.tolist(),
            "focal_px": f,
            "k1": k1,
            "k2": k2,
        }
        diagnostics = {"centre_source": source, "lens_fit_rms_px": rms_px, "condition_number": cond}
        return cls(H.reshape(-1)[:8], constants, diagnostics)

    def _prepare(self) -> None:
        super()._prepare()
        self._c = np.asarray(self.constants["centre_px"], float)
        c = self.constants
        self._lens = (float(c["focal_px"]), float(c["k1"]), float(c["k2"]))
        self._k = np.array([self._lens[1], self._lens[2], 0.0, 0.0])
        self._cu, self._cv = (float(x) for x in self._c)

    def _ideal_one(self, u: float, v: float) -> tuple[float, float]:
        f = self._lens[0]
        n, _ = undistort(np.array([(u - self._cu) / f, (v - self._cv) / f]), self._k)
        x, y = n.tolist()
        return self._cu + f * x, self._cv + f * y

    @property
    def distortion(self) -> tuple[float, float]:
        """(k1, k2) in OpenCV's f-normalised convention, with f = ``constants["focal_px"]``."""
        return self._lens[1], self._lens[2]

    def _ideal_px(self, uv_px: np.ndarray) -> np.ndarray:
        return undistort_px(uv_px, self._c, *self._lens)

    def _distorted_px(self, uv_px: np.ndarray) -> np.ndarray:
        f, k1, k2 = self._lens
        return self._c + f * distort((uv_px - self._c) / f, np.array([k1, k2, 0.0, 0.0]))


def undistort_px(uv_px: np.ndarray, centre, f: float, k1: float, k2: float) -> np.ndarray:
    """Ideal pixels from distorted ones for one lens (N, 2) (:func:`eyetohand.lens.undistort`); NaN
    where the lens cannot be inverted (beyond its fold)."""
    d = (np.asarray(uv_px, float) - centre) / f
    return centre + f * undistort(d, np.array([k1, k2, 0.0, 0.0]))[0]
