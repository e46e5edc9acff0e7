"""Synthetic images of the target with exact ground truth: the one renderer of the project.

A solid circle (``Target.diameter_mm``) on a metal strip (a rectangle of another grey around it),
lying on a plane z = const of the robot frame, seen by a pinhole camera with OpenCV lens distortion
(:class:`eyetohand.geometry.camera.Camera`, or any object with ``K``, ``dist``, ``R``, ``t``, ``image_size``),
over a textured belt (weak sinusoids plus a fine random grain, both fixed in the robot frame).

How a pixel gets its value:

* Every pixel corner is cast back through the camera (lens distortion inverted) onto the plane. For
  speed this is done exactly on a grid every 8 px and interpolated elsewhere; the corners of every
  pixel that an edge of the circle or the strip may cross are then cast back *exactly* (the
  interpolation error, < 1e-3 px, only decides which pixels count as such, with a wide margin).
* Edge pixels are supersampled (``supersample``² points per pixel, each with a linear coverage ramp
  over its own footprint), so a pixel's value is its exact area coverage to better than 1e-3 of a grey
  step; the others are shaded by what lies under their centre.
* Then Gaussian blur (``blur_px``, σ in px), vignetting (brightness × (1 − v·r²), r = 1 at the image
  corners), Gaussian noise (σ as a fraction of full scale, from a seeded Generator) and quantisation
  to 8 or 16 bits. A 2448×2048 image takes about 0.4–0.5 s (see ``tests/test_render.py``).

Truth (:class:`Truth`), all in px, OpenCV convention (pixel centres at integers):

* ``centre_px`` — the image of the circle's centre (perspective projection of the 3-D centre);
* ``ellipse_centre_px`` — the centre of the imaged ellipse: a least-squares conic fitted to 4096
  points of the circle's boundary projected through the camera (distortion included); without
  distortion the image is an exact conic, and :func:`exact_conic` gives it in closed form (the two
  agree to ~1e-9 px, tested);
* ``centroid_px`` — the area centroid of the imaged disc (the projected boundary as a polygon).

The ellipse's centre and the image of the circle's centre differ by the perspective bias of a tilted
view; the detector measures the former, so accuracy claims use ``ellipse_centre_px``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from eyetohand.geometry import Camera, as_camera

BELT_LEVEL = 0.35
STRIP_LEVEL = 0.85
CIRCLE_LEVEL = 0.08
BELT_WAVES = np.array([[0.9, 0.4], [-0.3, 1.3], [2.1, -1.7], [0.15, 0.05]])  # rad/mm
BELT_AMPLITUDES = np.array([0.03, 0.025, 0.015, 0.04])
BELT_PHASES = (0.3, 1.1, 2.0, 0.7)
GRAIN_TEXEL_MM = 0.2  # the belt grain's texel; a 512-texel tile repeats every 102.4 mm
_GRID_STEP_PX = 8  # exact back-projection every 8 px, interpolated between


@dataclass(frozen=True)
class Target:
    """What is rendered: a solid circle on a strip (along the tool's x axis) over a textured belt.
    Levels are fractions of full scale; ``strip_width_mm`` 0 means no strip. ``belt_grain``: σ of the
    belt's fine random texture (fraction of full scale), a fixed pattern chosen by ``belt_seed``."""

    diameter_mm: float = 5.0
    strip_width_mm: float = 8.0
    strip_length_mm: float = 60.0
    circle_level: float = CIRCLE_LEVEL
    strip_level: float = STRIP_LEVEL
    belt_level: float = BELT_LEVEL
    belt_phases: tuple[float, ...] = BELT_PHASES
    belt_grain: float = 0.02
    belt_seed: int = 0


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
        """Equivalent diameter √(major · minor) px."""
        return float(np.sqrt(self.axes_px[0] * self.axes_px[1]))

    @property
    def perspective_bias_px(self) -> float:
        """Distance (px) between the imaged ellipse's centre and the image of the circle's centre."""
        return float(np.hypot(*np.subtract(self.ellipse_centre_px, self.centre_px)))

    def to_dict(self) -> dict:
        return {
            "centre_px": list(self.centre_px),
            "ellipse_centre_px": list(self.ellipse_centre_px),
            "centroid_px": list(self.centroid_px),
            "axes_px": list(self.axes_px),
            "angle_deg": self.angle_deg,
        }


def project(camera, xyz_mm) -> np.ndarray:
    """Image points (N, 2) px of robot points (N, 3) mm through any camera with K, dist, R, t."""
    return as_camera(camera).robot_to_image(np.asarray(xyz_mm, float).reshape(-1, 3))


# ------------------------------------------------------------------ geometry helpers


def _plane_grid(cam: Camera, z_mm: float, step: int):
    """Exact plane points (ny, nx, 2) mm of the image points u, v = −½ + k·step (k = 0, 1, …) covering
    the image, and the node coordinates."""
    w, h = cam.image_size
    us = np.arange(math.ceil(w / step) + 1) * step - 0.5
    vs = np.arange(math.ceil(h / step) + 1) * step - 0.5
    uu, vv = np.meshgrid(us, vs)
    xyz = cam.image_to_robot(np.stack([uu, vv], axis=-1).reshape(-1, 2), z_mm)
    return xyz[:, :2].reshape(len(vs), len(us), 2)


def _interp(grid: np.ndarray, step: int, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear interpolation (float64) of a node grid from :func:`_plane_grid` at the image points
    u (nx,) × v (ny,): (ny, nx, 2)."""
    fu, fv = (u + 0.5) / step, (v + 0.5) / step
    iu = np.clip(np.floor(fu).astype(int), 0, grid.shape[1] - 2)
    iv = np.clip(np.floor(fv).astype(int), 0, grid.shape[0] - 2)
    au, av = (fu - iu)[None, :, None], (fv - iv)[:, None, None]
    g00, g01 = grid[iv][:, iu], grid[iv][:, iu + 1]
    g10, g11 = grid[iv + 1][:, iu], grid[iv + 1][:, iu + 1]
    return (1 - av) * ((1 - au) * g00 + au * g01) + av * ((1 - au) * g10 + au * g11)


def _belt_image(cam: Camera, grid: np.ndarray, step: int, target: Target) -> np.ndarray:
    """The belt (h, w) float32: sinusoids and grain of the plane coordinates, evaluated on a grid of
    half the image's resolution and interpolated (the texture is smooth at that scale)."""
    import cv2

    w, h = cam.image_size
    wh, hh = (w + 1) // 2, (h + 1) // 2
    # half-resolution sample k is at pixel 2k + ½; node n of the grid at pixel n·step − ½
    mx = np.ascontiguousarray(np.broadcast_to(((2 * np.arange(wh) + 1) / step).astype(np.float32), (hh, wh)))
    my = np.ascontiguousarray(
        np.broadcast_to(((2 * np.arange(hh) + 1) / step).astype(np.float32)[:, None], (hh, wh))
    )
    xy = cv2.remap(grid.astype(np.float32), mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    img = np.full((hh, wh), target.belt_level, np.float32)
    for (kx, ky), a, ph in zip(BELT_WAVES, BELT_AMPLITUDES, target.belt_phases, strict=False):
        img += np.float32(a) * np.sin(
            np.float32(kx) * xy[..., 0] + np.float32(ky) * xy[..., 1] + np.float32(ph)
        )
    if target.belt_grain > 0:
        tile = _grain_tile(target.belt_seed)
        img += np.float32(target.belt_grain) * cv2.remap(
            tile,
            xy[..., 0] / np.float32(GRAIN_TEXEL_MM),
            xy[..., 1] / np.float32(GRAIN_TEXEL_MM),
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_WRAP,
        )
    # back to full resolution: pixel j sits at half-resolution coordinate (j − ½)/2
    full = cv2.resize(img, (2 * wh, 2 * hh), interpolation=cv2.INTER_LINEAR)
    return np.ascontiguousarray(full[:h, :w])


_TILES: dict[int, np.ndarray] = {}


def _grain_tile(seed: int) -> np.ndarray:
    """A 512×512 float32 tile of unit-σ grain (white noise smoothed over ~1.5 texels), fixed by seed."""
    import cv2

    if seed not in _TILES:
        t = np.random.default_rng(seed).standard_normal((512, 512)).astype(np.float32)
        smooth = cv2.GaussianBlur(np.pad(t, 8, mode="wrap"), (0, 0), 1.5)[8:-8, 8:-8]  # periodic
        _TILES[seed] = (smooth / smooth.std()).astype(np.float32)
    return _TILES[seed]


def _signed_circle(local: np.ndarray, radius: float) -> np.ndarray:
    return np.hypot(local[..., 0], local[..., 1]) - radius


def _signed_box(local: np.ndarray, half: np.ndarray) -> np.ndarray:
    q = np.abs(local) - half
    outside = np.hypot(np.maximum(q[..., 0], 0), np.maximum(q[..., 1], 0))
    return np.where((q > 0).any(axis=-1), outside, q.max(axis=-1))


def _corner_stats(corners_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Plane points of the pixel centres (mean of the 4 corners) and each pixel's reach (half its
    longer diagonal), from the corners (h+1, w+1, 2)."""
    c00, c01 = corners_xy[:-1, :-1], corners_xy[:-1, 1:]
    c10, c11 = corners_xy[1:, :-1], corners_xy[1:, 1:]
    centre = 0.25 * (c00 + c01 + c10 + c11)
    d1, d2 = c11 - c00, c10 - c01
    reach = 0.5 * np.sqrt(np.maximum(d1[..., 0] ** 2 + d1[..., 1] ** 2, d2[..., 0] ** 2 + d2[..., 1] ** 2))
    return centre, reach


def _coverage(
    corners_xy: np.ndarray, d_centre: np.ndarray, reach: np.ndarray, to_local, signed, S: int
) -> np.ndarray:
    """Area fraction of each pixel inside a shape. ``corners_xy`` (h+1, w+1, 2) plane points of the pixel
    corners, ``d_centre`` the signed distance (mm) of the pixel centres from the shape's edge, ``reach``
    half a pixel's diagonal on the plane (mm); pixels an edge may cross are supersampled S×S
    (bilinear between the corners)."""
    cov = (d_centre < 0).astype(float)
    band = np.abs(d_centre) <= reach * 1.05 + 1e-9
    if not band.any():
        return cov
    iv, iu = np.nonzero(band)
    a = (np.arange(S) + 0.5) / S
    fu, fv = np.meshgrid(a, a)  # (S, S) fractions along u and v
    fu, fv = fu.ravel()[None, :, None], fv.ravel()[None, :, None]
    b00, b01 = corners_xy[iv, iu][:, None], corners_xy[iv, iu + 1][:, None]
    b10, b11 = corners_xy[iv + 1, iu][:, None], corners_xy[iv + 1, iu + 1][:, None]
    pts = (1 - fv) * ((1 - fu) * b00 + fu * b01) + fv * ((1 - fu) * b10 + fu * b11)
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


def exact_conic(camera, centre_mm, diameter_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """The image conic of a circle in a plane z = const through a camera *without* distortion, in
    closed form: C' = H⁻ᵀ C H⁻¹ with H = K [r1 r2 r3·z + t]. Returns (3×3 conic matrix of pixel
    homogeneous coordinates, its centre (2,) px). Lens distortion of ``camera`` is ignored."""
    cam = as_camera(camera)
    c = np.asarray(centre_mm, float).reshape(3)
    R, t = cam.R, cam.t
    H = cam.K @ np.column_stack([R[:, 0], R[:, 1], R[:, 2] * c[2] + t])
    r = diameter_mm / 2
    C = np.array([[1.0, 0.0, -c[0]], [0.0, 1.0, -c[1]], [-c[0], -c[1], c[0] ** 2 + c[1] ** 2 - r * r]])
    Hi = np.linalg.inv(H)
    Ci = Hi.T @ C @ Hi
    centre = np.linalg.solve(Ci[:2, :2], -Ci[:2, 2])
    return Ci, centre


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
    return Truth(
        (float(centre[0]), float(centre[1])),
        (float(ec[0]), float(ec[1])),
        (float(centroid[0]), float(centroid[1])),
        axes,
        ang,
    )


# ------------------------------------------------------------------ the renderer


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

    ``camera``: a :class:`~eyetohand.geometry.camera.Camera` or any object with ``K``, ``dist``, ``R``, ``t``,
    ``image_size``. ``blur_px``: Gaussian σ (px). ``noise``: σ as a fraction of full scale (2/255 ≈ 2
    grey levels of 8 bits). ``vignetting``: fractional darkening at the image corners. ``rng``: a
    Generator or a seed (the noise is the only randomness; the belt's grain is fixed by
    ``target.belt_seed``)."""
    import cv2

    if bits not in (8, 16):
        raise ValueError(f"bits must be 8 or 16, got {bits!r}")
    if blur_px < 0 or noise < 0 or not 0 <= vignetting < 1 or supersample < 1:
        raise ValueError("blur_px and noise must be >= 0, vignetting in [0, 1), supersample >= 1")
    cam = as_camera(camera)
    target = Target() if target is None else target
    rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    c = np.asarray(centre_mm, float).reshape(3)
    z = float(c[2])
    w, h = cam.image_size
    step = _GRID_STEP_PX
    grid = _plane_grid(cam, z, step)
    img = _belt_image(cam, grid, step, target)

    ca, sa = math.cos(math.radians(angle_deg)), math.sin(math.radians(angle_deg))
    rot = np.array([[ca, -sa], [sa, ca]])  # tool → robot

    def to_local(xy):
        return (xy - c[:2]) @ rot  # robot → tool frame (mm)

    # the region that holds the strip (or the circle), with a margin, in pixels
    half = np.array([target.strip_length_mm, target.strip_width_mm]) / 2
    has_strip = target.strip_width_mm > 0 and target.strip_length_mm > 0
    ext = half if has_strip else np.array([target.diameter_mm, target.diameter_mm]) / 2
    box = np.array([[sx * ext[0], sy * ext[1]] for sx in (-1, 1) for sy in (-1, 1)]) @ rot.T + c[:2]
    tt = np.linspace(0, 1, 9)[:, None]  # edges of the box too, since distortion bends them
    outline = np.vstack([box[i] + tt * (box[j] - box[i]) for i, j in ((0, 1), (1, 3), (3, 2), (2, 0))])
    uv = project(cam, np.column_stack([outline, np.full(len(outline), z)]))
    uv = uv[np.isfinite(uv).all(axis=1)]
    if len(uv):
        lo = np.floor(uv.min(axis=0)).astype(int) - 4
        hi = np.ceil(uv.max(axis=0)).astype(int) + 5
        x0, y0 = max(lo[0], 0), max(lo[1], 0)
        x1, y1 = min(hi[0], w), min(hi[1], h)
    else:
        x0 = y0 = x1 = y1 = 0
    if x1 > x0 and y1 > y0:
        us = np.arange(x0, x1 + 1) - 0.5
        vs = np.arange(y0, y1 + 1) - 0.5
        corners = _interp(grid, step, us, vs)
        # pixels an edge may cross (wide margin for the interpolation): their corners exactly
        centre, reach = _corner_stats(corners)
        local = to_local(centre)
        r = target.diameter_mm / 2
        d_circle = _signed_circle(local, r)
        near = np.abs(d_circle) <= 1.3 * reach
        if has_strip:
            d_box = _signed_box(local, half)
            near |= np.abs(d_box) <= 1.3 * reach
        need = np.zeros(corners.shape[:2], bool)
        need[:-1, :-1] |= near
        need[:-1, 1:] |= near
        need[1:, :-1] |= near
        need[1:, 1:] |= near
        iv, iu = np.nonzero(need)
        corners[iv, iu] = cam.image_to_robot(np.column_stack([us[iu], vs[iv]]), z)[:, :2]
        # the pixels near an edge again, from their exact corners
        sel = np.nonzero(near)
        c_near = corners[:-1, :-1][sel] + corners[:-1, 1:][sel] + corners[1:, :-1][sel] + corners[1:, 1:][sel]
        local_near = to_local(0.25 * c_near)
        d1 = corners[1:, 1:][sel] - corners[:-1, :-1][sel]
        d2 = corners[1:, :-1][sel] - corners[:-1, 1:][sel]
        reach[sel] = 0.5 * np.sqrt(np.maximum((d1**2).sum(-1), (d2**2).sum(-1)))
        d_circle[sel] = _signed_circle(local_near, r)
        roi = img[y0:y1, x0:x1].astype(float)
        if has_strip:
            d_box[sel] = _signed_box(local_near, half)
            cov = _coverage(corners, d_box, reach, to_local, lambda p: _signed_box(p, half), supersample)
            roi += (target.strip_level - roi) * cov
        cov = _coverage(corners, d_circle, reach, to_local, lambda p: _signed_circle(p, r), supersample)
        roi += (target.circle_level - roi) * cov
        img[y0:y1, x0:x1] = roi
    if blur_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_px)
    if vignetting > 0:
        rx = ((np.arange(w, dtype=np.float32) - (w - 1) / 2) ** 2)[None, :]
        ry = ((np.arange(h, dtype=np.float32) - (h - 1) / 2) ** 2)[:, None]
        img *= 1 - np.float32(vignetting / (((w - 1) / 2) ** 2 + ((h - 1) / 2) ** 2)) * (rx + ry)
    top = 255 if bits == 8 else 65535
    img *= np.float32(top)
    if noise > 0:
        img += np.float32(noise * top) * rng.standard_normal((h, w), dtype=np.float32)
    np.rint(img, out=img)
    np.clip(img, 0, top, out=img)
    out = img.astype(np.uint8 if bits == 8 else np.uint16)
    return out, circle_truth(cam, c, target.diameter_mm)


__all__ = ["Camera", "Target", "Truth", "circle_truth", "exact_conic", "project", "render"]
