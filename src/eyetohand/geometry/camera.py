"""A small vectorised pinhole camera with Brown–Conrady lens distortion, posed in the robot frame.

Conventions (the same as OpenCV's, so ``cv2.projectPoints`` / ``cv2.undistortPoints`` agree):

* Robot (base) frame: millimetres, z up; the belt is a plane z = const below the camera.
* Pose: ``Xc = R · X + t`` maps a robot point ``X`` (mm) to the camera frame (mm). ``R`` is stored as
  the Rodrigues vector ``rvec`` (rad), ``t`` as ``tvec_mm``. The camera centre in the robot frame is
  ``position_mm = −Rᵀ t``; the camera looks along its +z axis, image u along its +x, v along its +y.
* Normalised image coordinates ``x = Xc/Zc, y = Yc/Zc``; distortion (OpenCV order
  ``k1 k2 p1 p2 k3``)::

      r² = x² + y²,  g = 1 + k1 r² + k2 r⁴ + k3 r⁶
      x_d = x g + 2 p1 x y + p2 (r² + 2 x²)
      y_d = y g + p1 (r² + 2 y²) + 2 p2 x y

* Pixels: ``u = fx_px · x_d + cx_px``, ``v = fy_px · y_d + cy_px``; pixel centres at integer
  coordinates (pixel (row i, column j) covers u ∈ [j − ½, j + ½], v ∈ [i − ½, i + ½]).

The lens maths (distortion, its inversion with a convergence test, Rodrigues) is
:mod:`eyetohand.geometry.lens`, shared with the models: points where the inversion does not converge (beyond
the fold of a strongly distorting lens) come back as NaN rather than as a wrong ray.

Build a camera with :meth:`Camera.looking_down` (height and tilt over the belt), :meth:`Camera.look_at`
(eye and target points) or :meth:`Camera.from_opencv` (``K``, ``dist``, ``R``/``rvec``, ``t``);
store it with :meth:`Camera.to_dict` / :meth:`Camera.from_dict`.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from eyetohand.core import InputError
from eyetohand.geometry.lens import distort, matrix_to_rodrigues, rodrigues_to_matrix, undistort


def _as_points(a, dim: int, what: str) -> tuple[np.ndarray, tuple[int, ...]]:
    """``a`` as (N, dim) float64 and the leading shape to restore ((,) for a single point)."""
    arr = np.asarray(a, dtype=float)
    if arr.shape[-1:] != (dim,):
        raise InputError(f"{what}: expected an array of shape (N, {dim}) or ({dim},), got {arr.shape}")
    return arr.reshape(-1, dim), arr.shape[:-1]


@dataclass(frozen=True, eq=False)
class Camera:
    """Pinhole camera (intrinsics in px, distortion, pose in the robot frame). See the module docstring.

    Attributes are plain numbers and tuples, so a camera is immutable and serialises as is;
    ``K``, ``dist``, ``R``, ``t`` and ``image_size`` give the OpenCV views of it.
    """

    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    width_px: int
    height_px: int
    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    rvec: tuple[float, float, float] = (0.0, 0.0, 0.0)  # robot → camera rotation, Rodrigues (rad)
    tvec_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)  # Xc = R·X + t
    if TYPE_CHECKING:  # what __post_init__ derives once; not fields (to_dict, from_dict, eq ignore them)
        _R: np.ndarray = field(init=False)
        _dist: np.ndarray = field(init=False)
        _f: np.ndarray = field(init=False)
        _c: np.ndarray = field(init=False)
        _centre: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        for name in ("fx_px", "fy_px", "cx_px", "cy_px", "k1", "k2", "k3", "p1", "p2"):
            v = float(getattr(self, name))
            if not math.isfinite(v):
                raise InputError(f"camera.{name}: must be a finite number, got {v!r}")
            object.__setattr__(self, name, v)
        if self.fx_px <= 0 or self.fy_px <= 0:
            raise InputError(f"camera: focal lengths must be positive, got {self.fx_px}, {self.fy_px}")
        for name in ("width_px", "height_px"):
            v = getattr(self, name)
            if int(v) != v or int(v) < 1:
                raise InputError(f"camera.{name}: must be a positive whole number of px, got {v!r}")
            object.__setattr__(self, name, int(v))
        for name in ("rvec", "tvec_mm"):
            vec = np.asarray(getattr(self, name), float).reshape(-1)
            if vec.shape != (3,) or not np.isfinite(vec).all():
                raise InputError(f"camera.{name}: expected 3 finite numbers, got {getattr(self, name)!r}")
            object.__setattr__(self, name, tuple(float(x) for x in vec))
        object.__setattr__(self, "_R", rodrigues_to_matrix(np.array(self.rvec)))
        object.__setattr__(self, "_dist", np.array([self.k1, self.k2, self.p1, self.p2, self.k3]))
        object.__setattr__(self, "_f", np.array([self.fx_px, self.fy_px]))
        object.__setattr__(self, "_c", np.array([self.cx_px, self.cy_px]))
        object.__setattr__(self, "_centre", -self._R.T @ np.array(self.tvec_mm))

    # ------------------------------------------------------------------ views

    @property
    def K(self) -> np.ndarray:
        """3×3 intrinsic matrix (px)."""
        return np.array([[self.fx_px, 0.0, self.cx_px], [0.0, self.fy_px, self.cy_px], [0.0, 0.0, 1.0]])

    @property
    def dist(self) -> np.ndarray:
        """Distortion coefficients in OpenCV order (k1, k2, p1, p2, k3)."""
        return np.array([self.k1, self.k2, self.p1, self.p2, self.k3])

    @property
    def R(self) -> np.ndarray:
        """3×3 rotation robot → camera (a copy)."""
        return self._R.copy()

    @property
    def t(self) -> np.ndarray:
        """Translation (mm): Xc = R·X + t."""
        return np.array(self.tvec_mm)

    @property
    def image_size(self) -> tuple[int, int]:
        """(width, height) px."""
        return (self.width_px, self.height_px)

    @property
    def position_mm(self) -> np.ndarray:
        """The camera centre in the robot frame (mm)."""
        return -self._R.T @ np.array(self.tvec_mm)

    @property
    def optical_axis(self) -> np.ndarray:
        """Unit viewing direction (camera +z) in the robot frame."""
        return self._R[2].copy()

    @property
    def tilt_deg(self) -> float:
        """Angle between the optical axis and straight down (robot −z), degrees."""
        return math.degrees(math.acos(float(np.clip(-self._R[2, 2], -1.0, 1.0))))

    # ------------------------------------------------------------------ constructors

    @classmethod
    def from_opencv(cls, K, dist, rotation, t_mm, image_size) -> Camera:
        """From OpenCV arrays: ``K`` 3×3 (zero skew), ``dist`` (k1, k2, p1, p2[, k3]) or None,
        ``rotation`` a Rodrigues vector (3,) or matrix (3, 3) robot → camera, ``t_mm`` (3,),
        ``image_size`` (w, h) px."""
        K = np.asarray(K, float)
        if K.shape != (3, 3) or abs(K[0, 1]) > 1e-12 or np.any(K[2] != [0, 0, 1]):
            raise InputError(f"K: expected a 3x3 camera matrix without skew, got {K.tolist()!r}")
        d = np.zeros(5) if dist is None else np.asarray(dist, float).reshape(-1)
        if d.size not in (4, 5):
            raise InputError(f"dist: expected 4 or 5 coefficients (k1 k2 p1 p2 [k3]), got {d.size}")
        d = np.concatenate([d, np.zeros(5 - d.size)])
        rot = np.asarray(rotation, float)
        rvec = matrix_to_rodrigues(rot) if rot.shape == (3, 3) else rot.reshape(3)
        w, h = image_size
        return cls(
            K[0, 0],
            K[1, 1],
            K[0, 2],
            K[1, 2],
            w,
            h,
            k1=d[0],
            k2=d[1],
            k3=d[4],
            p1=d[2],
            p2=d[3],
            rvec=tuple(rvec),
            tvec_mm=tuple(np.asarray(t_mm, float).reshape(3)),
        )

    @classmethod
    def look_at(
        cls,
        eye_mm,
        target_mm,
        *,
        image_size=(2448, 2048),
        focal_px: float = 4637.7,
        aspect: float = 1.0,
        principal_point_px=None,
        dist=(0.0, 0.0, 0.0, 0.0, 0.0),
        up=(0.0, 1.0, 0.0),
    ) -> Camera:
        """A camera at ``eye_mm`` (robot frame) whose optical axis passes through ``target_mm``.

        ``up``: a robot-frame direction that appears pointing up the image (towards −v); it must not
        be parallel to the optical axis. ``focal_px`` is fx; fy = ``aspect`` · fx. The principal point
        defaults to the image centre ((w − 1)/2, (h − 1)/2). ``dist``: (k1, k2, p1, p2[, k3])."""
        eye = np.asarray(eye_mm, float).reshape(3)
        z = np.asarray(target_mm, float).reshape(3) - eye
        if np.linalg.norm(z) == 0:
            raise InputError("look_at: eye and target are the same point")
        z /= np.linalg.norm(z)
        u = np.asarray(up, float).reshape(3)
        y = -(u - (u @ z) * z)
        if np.linalg.norm(y) < 1e-9 * max(float(np.linalg.norm(u)), 1e-300):
            raise InputError("look_at: 'up' is parallel to the optical axis")
        y /= np.linalg.norm(y)
        x = np.cross(y, z)
        R = np.vstack([x, y, z])
        w, h = image_size
        pp = ((w - 1) / 2, (h - 1) / 2) if principal_point_px is None else principal_point_px
        K = np.array([[focal_px, 0.0, pp[0]], [0.0, aspect * focal_px, pp[1]], [0.0, 0.0, 1.0]])
        return cls.from_opencv(K, dist, R, -R @ eye, (w, h))

    @classmethod
    def looking_down(
        cls,
        image_size=(2448, 2048),
        *,
        focal_px: float = 4637.7,
        height_mm: float = 300.0,
        tilt_deg: float = 8.0,
        tilt_direction_deg: float = 30.0,
        yaw_deg: float = 25.0,
        dist=(-0.08, 0.12, 0.0002, -0.0001, 0.0),
        pp_offset_px=(12.0, -8.0),
        target_mm=(0.0, 0.0, 0.0),
    ) -> Camera:
        """A camera ``height_mm`` above the plane z = ``target_mm[2]``, its optical axis ``tilt_deg``
        from vertical and meeting that plane at ``target_mm``; the axis leans towards the robot
        direction ``tilt_direction_deg`` (from +x), image u is ``yaw_deg`` from robot +x (projected on
        the image plane). Square pixels of ``focal_px``; principal point ``pp_offset_px`` from the
        image centre; ``dist`` (k1, k2, p1, p2, k3). The defaults are the simulator's lens: a 16 mm
        lens on 3.45 µm pixels, 2448×2048."""
        if not 0 <= tilt_deg < 90:
            raise InputError(f"tilt_deg: expected 0 <= tilt < 90, got {tilt_deg}")
        if height_mm <= 0:
            raise InputError(f"height_mm: expected a positive height, got {height_mm}")
        w, h = image_size
        K = np.array(
            [
                [focal_px, 0.0, (w - 1) / 2 + pp_offset_px[0]],
                [0.0, focal_px, (h - 1) / 2 + pp_offset_px[1]],
                [0.0, 0.0, 1.0],
            ]
        )
        tilt, az, yaw = (math.radians(a) for a in (tilt_deg, tilt_direction_deg, yaw_deg))
        z_cam = np.array([math.sin(tilt) * math.cos(az), math.sin(tilt) * math.sin(az), -math.cos(tilt)])
        centre = np.asarray(target_mm, float).reshape(3) - (height_mm / math.cos(tilt)) * z_cam
        x0 = np.array([math.cos(yaw), math.sin(yaw), 0.0])
        x_cam = x0 - (x0 @ z_cam) * z_cam
        x_cam /= np.linalg.norm(x_cam)
        R = np.vstack([x_cam, np.cross(z_cam, x_cam), z_cam])
        return cls.from_opencv(K, dist, R, -R @ centre, (w, h))

    @classmethod
    def from_dict(cls, d: dict) -> Camera:
        """Inverse of :meth:`to_dict` (derived keys such as ``position_mm`` are ignored)."""
        names = {f.name for f in fields(cls)}
        derived = {"position_mm", "K", "dist_k1_k2_p1_p2_k3", "image_size"}
        unknown = sorted(set(d) - names - derived)
        if unknown:
            raise InputError(f"camera: unknown key {unknown[0]!r}; valid keys: {', '.join(sorted(names))}")
        missing = [n for n in ("fx_px", "fy_px", "cx_px", "cy_px", "width_px", "height_px") if n not in d]
        if missing:
            raise InputError(f"camera: missing key {missing[0]!r}")
        kwargs: dict[str, Any] = {
            k: (tuple(v) if k in ("rvec", "tvec_mm") else v) for k, v in d.items() if k in names
        }
        return cls(**kwargs)

    def to_dict(self) -> dict:
        """Plain JSON-able dict of the fields, plus ``position_mm`` for readers."""
        out = {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self).items()}
        out["position_mm"] = self.position_mm.tolist()
        return out

    def with_pose(self, rotation, t_mm) -> Camera:
        """The same intrinsics with another pose (``rotation`` Rodrigues (3,) or matrix (3, 3))."""
        rot = np.asarray(rotation, float)
        rvec = matrix_to_rodrigues(rot) if rot.shape == (3, 3) else rot.reshape(3)
        return replace(self, rvec=tuple(rvec), tvec_mm=tuple(np.asarray(t_mm, float).reshape(3)))

    # ------------------------------------------------------------------ the lens

    def distort(self, xy) -> np.ndarray:
        """Distorted normalised coordinates of ideal ones, (N, 2) → (N, 2) (:func:`.lens.distort`)."""
        p, lead = _as_points(xy, 2, "xy")
        return distort(p, self._dist).reshape(*lead, 2)

    def undistort(self, xy_d) -> np.ndarray:
        """Ideal normalised coordinates of distorted ones (N, 2) (:func:`eyetohand.geometry.lens.undistort`:
        fixed-point start, Newton to 1e-14); NaN where the iteration does not converge."""
        p, lead = _as_points(xy_d, 2, "xy_d")
        return undistort(p, self._dist)[0].reshape(*lead, 2)

    # ------------------------------------------------------------------ projections

    def robot_to_camera(self, xyz_mm) -> np.ndarray:
        """Camera-frame coordinates (mm) of robot points, (N, 3) → (N, 3)."""
        p, lead = _as_points(xyz_mm, 3, "xyz_mm")
        return (p @ self._R.T + np.array(self.tvec_mm)).reshape(*lead, 3)

    def normalized_to_image(self, xy) -> np.ndarray:
        """Pixels of ideal normalised coordinates (distortion applied), (N, 2) → (N, 2)."""
        return self.distort(xy) * self._f + self._c

    def image_to_normalized(self, uv_px) -> np.ndarray:
        """Ideal normalised coordinates of pixels (distortion removed), (N, 2) → (N, 2)."""
        p, lead = _as_points(uv_px, 2, "uv_px")
        return undistort((p - self._c) / self._f, self._dist)[0].reshape(*lead, 2)

    def robot_to_image(self, xyz_mm) -> np.ndarray:
        """Pixels (N, 2) of robot points (N, 3) mm, lens distortion included; NaN for points not in
        front of the camera."""
        p, lead = _as_points(xyz_mm, 3, "xyz_mm")
        pc = p @ self._R.T + np.array(self.tvec_mm)
        z = pc[:, 2:]
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = pc[:, :2] / np.where(z > 0, z, np.nan)
        return (distort(xy, self._dist) * self._f + self._c).reshape(*lead, 2)

    def _directions(self, uv_px) -> tuple[np.ndarray, tuple[int, ...]]:
        """Unnormalised robot-frame ray directions Rᵀ·(x, y, 1) of pixels, (N, 3), and the lead shape."""
        p, lead = _as_points(uv_px, 2, "uv_px")
        n = undistort((p - self._c) / self._f, self._dist)[0]
        return n @ self._R[:2] + self._R[2], lead

    def image_to_ray(self, uv_px) -> tuple[np.ndarray, np.ndarray]:
        """The viewing rays of pixels: (origin (3,) mm = the camera centre, unit directions (N, 3)
        in the robot frame)."""
        d, lead = self._directions(uv_px)
        d = d / np.linalg.norm(d, axis=-1, keepdims=True)
        return self.position_mm, d.reshape(*lead, 3)

    def image_to_robot(self, uv_px, z_mm) -> np.ndarray:
        """Robot points (N, 3) mm seen at pixels ``uv_px`` (N, 2) on the plane z = ``z_mm`` (scalar or
        (N,)). NaN where the ray does not meet the plane in front of the camera."""
        d, lead = self._directions(uv_px)
        c = self._centre
        z = np.asarray(z_mm, float).reshape(-1)
        with np.errstate(divide="ignore", invalid="ignore"):
            s = (z - c[2]) / d[:, 2]
        s[~(s > 0)] = np.nan
        out = c + s[:, None] * d
        out[:, 2] = np.where(np.isnan(s), np.nan, z)  # exactly the plane's height
        return out.reshape(*lead, 3)

    def in_image(self, uv_px, margin_px: float = 0.0) -> np.ndarray:
        """Whether pixels lie inside the image (pixel area, −½ … w − ½), ``margin_px`` inside it."""
        p, lead = _as_points(uv_px, 2, "uv_px")
        lo = -0.5 + margin_px
        ok = (
            (p[:, 0] >= lo)
            & (p[:, 0] <= self.width_px - 0.5 - margin_px)
            & (p[:, 1] >= lo)
            & (p[:, 1] <= self.height_px - 0.5 - margin_px)
        )
        return ok.reshape(lead)

    # the names the renderer and the simulator use
    def project(self, xyz_mm) -> np.ndarray:
        """Alias of :meth:`robot_to_image`."""
        return self.robot_to_image(xyz_mm)


def as_camera(camera) -> Camera:
    """A :class:`Camera` from any object with OpenCV-style ``K``, ``dist``, ``R``, ``t`` and
    ``image_size`` (such as the simulator's hidden camera); a Camera is returned as is."""
    if isinstance(camera, Camera):
        return camera
    try:
        return Camera.from_opencv(camera.K, camera.dist, camera.R, camera.t, camera.image_size)
    except AttributeError:
        raise InputError(
            f"expected a camera with K, dist, R, t and image_size, got {type(camera).__name__}"
        ) from None


__all__ = ["Camera", "as_camera"]
