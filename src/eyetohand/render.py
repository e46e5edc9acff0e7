"""Synthetic images of the target with exact ground truth: the one renderer of the project.

A solid circle (``Target.diameter_mm``) on a metal strip, lying on a plane z = const of the robot frame,
seen by a pinhole camera with OpenCV lens distortion (``k1 k2 p1 p2 k3``), over a textured belt.
Each pixel centre is cast back through the camera (lens distortion inverted) onto the plane and shaded
by what lies there. Pixels that an edge of the circle or the strip crosses are supersampled
(``supersample``² points per pixel, each with a linear coverage ramp over its own footprint), so the
pixel value is the exact area coverage to better than 1e-3 of a grey step. Then Gaussian blur
(``blur_px``, σ in px), vignetting (brightness × (1 − v·r²), r = 1 at the image corners), Gaussian
noise (σ as a fraction of full scale, from a seeded Generator) and quantisation to 8 or 16 bits.

Truth (:class:`Truth`), all in px, OpenCV convention (pixel centres at integers):

* ``centre_px`` — the image of the circle's centre (perspective projection of the 3-D centre);
* ``ellipse_centre_px`` — the centre of the imaged ellipse: a least-squares conic fitted to 4096
  points of the circle's boundary projected through the camera (distortion included);
* ``centroid_px`` — the area centroid of the imaged disc (the projected boundary as a polygon).

The ellipse's centre and the image of the circle's centre differ by the perspective bias of a tilted
view; the detector measures the former, so accuracy claims use ``ellipse_centre_px``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

BELT_LEVEL = 0.35
STRIP_LEVEL = 0.85
CIRCLE_LEVEL = 0.08
BELT_WAVES = np.array([[0.9, 0.4], [-0.3, 1.3], [2.1, -1.7], [0.15, 0.05]])  # rad/mm
BELT_AMPLITUDES = np.array([0.03, 0.025, 0.015, 0.04])
BELT_PHASES = (0.3, 1.1, 2.0, 0.7)
_UNDISTORT = (3, 50, 1e-12)  # cv2.TERM_CRITERIA_COUNT | EPS, 50 iterations, 1e-12


@dataclass(frozen=True, eq=False)
class Camera:
    """A pinhole camera: ``K`` (3×3, px), ``dist`` (k1, k2, p1, p2, k3), pose ``R``, ``t`` with
    Xc = R·X + t (mm, robot frame), ``image_size`` (w, h) px. The simulator's hidden camera has the same
    attributes and can be passed wherever a Camera is expected."""

    K: np.ndarray
    dist: np.ndarray
    R: np.ndarray
    t: np.ndarray
    image_size: tuple[int, int]

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
    ) -> Camera:
        """A camera ``height_mm`` above the point (0, 0, 0), its optical axis ``tilt_deg`` from vertical
        (meeting the plane z = 0 at the origin), image u axis ``yaw_deg`` from robot +x."""
        w, h = image_size
        K = np.array([[focal_px, 0.0, (w - 1) / 2 + pp_offset_px[0]],
                      [0.0, focal_px, (h - 1) / 2 + pp_offset_px[1]], [0.0, 0.0, 1.0]])
        tilt, az, yaw = (math.radians(a) for a in (tilt_deg, tilt_direction_deg, yaw_deg))
        z_cam = np.array([math.sin(tilt) * math.cos(az), math.sin(tilt) * math.sin(az), -math.cos(tilt)])
        centre = -(height_mm / math.cos(tilt)) * z_cam
        x0 = np.array([math.cos(yaw), math.sin(yaw), 0.0])
        x_cam = x0 - (x0 @ z_cam) * z_cam
        x_cam /= np.linalg.norm(x_cam)
        R = np.vstack([x_cam, np.cross(z_cam, x_cam), z_cam])
        return cls(K, np.asarray(dist, float), R, -R @ centre, (int(w), int(h)))

    def project(self, xyz_mm) -> np.ndarray:
        """Image points (N, 2) px of robot points (N, 3) mm, lens distortion included."""
        return project(self, xyz_mm)


def project(camera, xyz_mm) -> np.ndarray:
    """Image points (N, 2) px of robot points (N, 3) mm through any camera with K, dist, R, t."""
    import cv2

    xyz = np.asarray(xyz_mm, float).reshape(-1, 3)
    uv, _ = cv2.projectPoints(xyz, cv2.Rodrigues(np.asarray(camera.R, float))[0],
                              np.asarray(camera.t, float).reshape(3), np.asarray(camera.K, float),
                              np.asarray(camera.dist, float))
    return uv.reshape(-1, 2)


@dataclass(frozen=True)
class Target:
    """What is rendered: a solid circle on a strip (along the tool's x axis) over a textured belt.
    Levels are fractions of full scale; ``strip_width_mm`` 0 means no strip."""

    diameter_mm: float = 5.0
    strip_width_mm: float = 8.0
    strip_length_mm: float = 60.0
    circle_level: float = CIRCLE_LEVEL
    strip_level: float = STRIP_LEVEL
    belt_level: float = BELT_LEVEL
    belt_phases: tuple[float, ...] = BELT_PHASES


@dataclass(frozen=True)
class Truth:
    """Exact geometry of one rendered circle (px): see the module docstring."""

    centre_px: tuple[float, float]
    ellipse_centre_px: tuple[float, float]
    centroid_px: tuple[float, float]
    axes_px: tuple[float, float]  # full lengths of the fitted ellipse's axes
    angle_deg: float

    @property
    def diameter_px(self) -> float:
        return float(np.sqrt(self.axes_px[0] * self.axes_px[1]))

    def to_dict(self) -> dict:
        return {"centre_px": list(self.centre_px), "ellipse_centre_px": list(self.ellipse_centre_px),
                "centroid_px": list(self.centroid_px), "axes_px": list(self.axes_px),
                "angle_deg": self.angle_deg}


@dataclass
class _Grid:
    """Undistorted normalised rays through every pixel corner, (h+1, w+1, 2), cached per camera."""

    rays: np.ndarray
    rot: np.ndarray = field(repr=False)  # R^T
    centre: np.ndarray = field(repr=False)


_GRIDS: dict[int, tuple[object, _Grid]] = {}


def _grid(camera) -> _Grid:
    key = id(camera)
    hit = _GRIDS.get(key)
    if hit is not None and hit[0] is camera:
        return hit[1]
    import cv2

    w, h = camera.image_size
    uu, vv = np.meshgrid(np.arange(w + 1, dtype=float) - 0.5, np.arange(h + 1, dtype=float) - 0.5)
    pts = np.stack([uu.ravel(), vv.ravel()], axis=1).reshape(-1, 1, 2)
    n = cv2.undistortPoints(pts, camera.K, camera.dist, criteria=_UNDISTORT).reshape(h + 1, w + 1, 2)
    R = np.asarray(camera.R, float)
    g = _Grid(n, R.T, -R.T @ np.asarray(camera.t, float))
    if len(_GRIDS) > 4:
        _GRIDS.clear()
    _GRIDS[key] = (camera, g)
    return g


def _on_plane(g: _Grid, n: np.ndarray, z_mm: float) -> np.ndarray:
    """Points (..., 2) mm where rays with normalised coordinates ``n`` (..., 2) meet the plane z."""
    Rt = g.rot
    rx = Rt[0, 0] * n[..., 0] + Rt[0, 1] * n[..., 1] + Rt[0, 2]
    ry = Rt[1, 0] * n[..., 0] + Rt[1, 1] * n[..., 1] + Rt[1, 2]
    rz = Rt[2, 0] * n[..., 0] + Rt[2, 1] * n[..., 1] + Rt[2, 2]
    s = (z_mm - g.centre[2]) / rz
    return np.stack([g.centre[0] + s * rx, g.centre[1] + s * ry], axis=-1)


def _belt(xy: np.ndarray, target: Target) -> np.ndarray:
    """Belt texture fixed in the robot frame: a few weak sinusoids of the plane coordinates."""
    t = xy @ BELT_WAVES.T + np.asarray(target.belt_phases, float)
    return target.belt_level + (BELT_AMPLITUDES * np.sin(t)).sum(axis=-1)


def _signed_circle(local: np.ndarray, radius: float) -> np.ndarray:
    return np.hypot(local[..., 0], local[..., 1]) - radius


def _signed_box(local: np.ndarray, half: np.ndarray) -> np.ndarray:
    q = np.abs(local) - half
    outside = np.hypot(np.maximum(q[..., 0], 0), np.maximum(q[..., 1], 0))
    return np.where((q > 0).any(axis=-1), outside, q.max(axis=-1))


def _coverage(corners_xy: np.ndarray, to_local, signed, S: int) -> np.ndarray:
    """Area fraction of each pixel inside a shape. ``corners_xy`` (h+1, w+1, 2) plane points of the pixel
    corners; pixels an edge may cross are supersampled S×S (bilinear between the corners)."""
    c00, c01 = corners_xy[:-1, :-1], corners_xy[:-1, 1:]
    c10, c11 = corners_xy[1:, :-1], corners_xy[1:, 1:]
    centre = 0.25 * (c00 + c01 + c10 + c11)
    reach = 0.5 * np.maximum(np.linalg.norm(c11 - c00, axis=-1), np.linalg.norm(c10 - c01, axis=-1))
    d = signed(to_local(centre))
    cov = (d < 0).astype(float)
    band = np.abs(d) <= reach * 1.05 + 1e-9
    if not band.any():
        return cov
    a = (np.arange(S) + 0.5) / S
    fu, fv = np.meshgrid(a, a)  # (S, S) fractions along u and v
    fu, fv = fu.ravel(), fv.ravel()
    b00, b01, b10, b11 = (c[band][:, None, :] for c in (c00, c01, c10, c11))
    pts = ((1 - fv)[None, :, None] * ((1 - fu)[None, :, None] * b00 + fu[None, :, None] * b01)
           + fv[None, :, None] * ((1 - fu)[None, :, None] * b10 + fu[None, :, None] * b11))
    ds = signed(to_local(pts))
    sub = (2 * reach[band] / (S * math.sqrt(2)))[:, None]  # a sub-pixel's width (mm)
    cov[band] = np.clip(0.5 - ds / sub, 0.0, 1.0).mean(axis=1)
    return cov


def _fit_conic_centre(pts: np.ndarray) -> tuple[np.ndarray, tuple[float, float], float]:
    """Least-squares conic through points (N, 2): centre, full axes lengths, angle (deg)."""
    m = pts.mean(axis=0)
    s = np.sqrt(((pts - m) ** 2).sum(axis=1).mean())
    x, y = ((pts - m) / s).T
    D = np.column_stack([x * x, x * y, y * y, x, y, np.ones_like(x)])
    a, b, c, d, e, f = np.linalg.svd(D, full_matrices=False)[2][-1]
    M = np.array([[2 * a, b], [b, 2 * c]])
    cx, cy = np.linalg.solve(M, [-d, -e])
    f0 = f + 0.5 * (d * cx + e * cy)
    ev, evec = np.linalg.eigh(np.array([[a, b / 2], [b / 2, c]]))
    axes = 2 * np.sqrt(-f0 / ev) * s
    ang = math.degrees(math.atan2(evec[1, 0], evec[0, 0]))
    return m + s * np.array([cx, cy]), (float(axes[0]), float(axes[1])), ang


def circle_truth(camera, centre_mm, diameter_mm: float, n: int = 4096) -> Truth:
    """Exact image geometry of a circle of ``diameter_mm`` centred at ``centre_mm`` (x, y, z) lying in a
    plane z = const: see the module docstring."""
    c = np.asarray(centre_mm, float)
    th = 2 * np.pi * np.arange(n) / n
    r = diameter_mm / 2
    ring = np.column_stack([c[0] + r * np.cos(th), c[1] + r * np.sin(th), np.full(n, c[2])])
    uv = project(camera, np.vstack([c[None], ring]))
    centre, b = uv[0], uv[1:]
    x, y = b[:, 0] - b[:, 0].mean(), b[:, 1] - b[:, 1].mean()
    x1, y1 = np.roll(x, -1), np.roll(y, -1)
    cross = x * y1 - x1 * y
    area = cross.sum() / 2
    centroid = np.array([((x + x1) * cross).sum(), ((y + y1) * cross).sum()]) / (6 * area) + b.mean(axis=0)
    ec, axes, ang = _fit_conic_centre(b)
    return Truth((float(centre[0]), float(centre[1])), (float(ec[0]), float(ec[1])),
                 (float(centroid[0]), float(centroid[1])), axes, ang)


def render(
    camera,
    centre_mm,
    *,
    angle_deg: float = 0.0,
    target: Target | None = None,
    blur_px: float = 1.0,
    noise: float = 2.0 / 255,
    vignetting: float = 0.25,
    bits: int = 8,
    rng: np.random.Generator | int | None = 0,
    supersample: int = 8,
) -> tuple[np.ndarray, Truth]:
    """One image (h, w) uint8 or uint16 of ``target`` whose circle's centre is at ``centre_mm``
    (x, y, z mm, robot frame), the strip turned by ``angle_deg`` about z; and the :class:`Truth`.

    ``noise`` is σ as a fraction of full scale (2/255 ≈ 2 grey levels of 8 bits); ``rng`` a Generator
    or a seed (the noise is the only randomness)."""
    import cv2

    if bits not in (8, 16):
        raise ValueError(f"bits must be 8 or 16, got {bits!r}")
    target = Target() if target is None else target
    rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    c = np.asarray(centre_mm, float)
    g = _grid(camera)
    w, h = camera.image_size
    corners = _on_plane(g, g.rays, float(c[2]))
    centres = 0.25 * (corners[:-1, :-1] + corners[:-1, 1:] + corners[1:, :-1] + corners[1:, 1:])
    img = _belt(centres, target)

    ca, sa = math.cos(math.radians(angle_deg)), math.sin(math.radians(angle_deg))
    rot = np.array([[ca, -sa], [sa, ca]])  # tool → robot

    def to_local(xy):
        return (xy - c[:2]) @ rot  # robot → tool frame (mm)

    # the region that holds the strip (or the circle), with a margin, in pixels
    half = np.array([target.strip_length_mm, target.strip_width_mm]) / 2
    has_strip = target.strip_width_mm > 0 and target.strip_length_mm > 0
    ext = half if has_strip else np.array([target.diameter_mm, target.diameter_mm]) / 2
    box = np.array([[sx * ext[0], sy * ext[1]] for sx in (-1, 1) for sy in (-1, 1)]) @ rot.T + c[:2]
    # edges of the box too, since distortion bends them
    tt = np.linspace(0, 1, 9)[:, None]
    outline = np.vstack([box[i] + tt * (box[j] - box[i]) for i, j in ((0, 1), (1, 3), (3, 2), (2, 0))])
    uv = project(camera, np.column_stack([outline, np.full(len(outline), c[2])]))
    lo = np.floor(uv.min(axis=0)).astype(int) - 4
    hi = np.ceil(uv.max(axis=0)).astype(int) + 5
    x0, y0 = max(lo[0], 0), max(lo[1], 0)
    x1, y1 = min(hi[0], w), min(hi[1], h)
    if x1 > x0 and y1 > y0:
        sub = corners[y0 : y1 + 1, x0 : x1 + 1]
        roi = img[y0:y1, x0:x1]
        if has_strip:
            cov = _coverage(sub, to_local, lambda p: _signed_box(p, half), supersample)
            roi += (target.strip_level - roi) * cov
        r = target.diameter_mm / 2
        cov = _coverage(sub, to_local, lambda p: _signed_circle(p, r), supersample)
        roi += (target.circle_level - roi) * cov
    if blur_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_px)
    if vignetting > 0:
        yy, xx = np.ogrid[0:h, 0:w]
        r2 = ((xx - (w - 1) / 2) ** 2 + (yy - (h - 1) / 2) ** 2) / (((w - 1) / 2) ** 2 + ((h - 1) / 2) ** 2)
        img = img * (1 - vignetting * r2)
    if noise > 0:
        img = img + rng.normal(0.0, noise, img.shape)
    top = 255 if bits == 8 else 65535
    out = np.clip(np.rint(img * top), 0, top).astype(np.uint8 if bits == 8 else np.uint16)
    return out, circle_truth(camera, c, target.diameter_mm)


__all__ = ["Camera", "Target", "Truth", "circle_truth", "project", "render"]
