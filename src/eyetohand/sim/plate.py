"""A calibration plate in the virtual cell: its image, the robot's touches of its corners, check points.

The plate lies on the belt (z = ``belt.z_mm`` + ``lift_mm``), turned by ``yaw_deg`` about z and
tilted by ``tilt_deg`` (a table is never quite level), centred where the camera's optical axis meets
it. Its image is rendered exactly: every pixel is cast back through the hidden camera (lens
included) onto the plate's plane — exactly on a grid every 8 px, bilinear between (< 1e-3 px) — and
shaded by the pattern box-filtered over the pixel's footprint (a chessboard square's edge, a dot's
rim: exact area coverage for a separable box), then blurred, noised and quantised as the cell's
``render`` section says.

Touches: the corners labelled A–D (:meth:`~eyetohand.vision.plate.PlateSpec.corner_labels`), first
``n``; the robot reads the pointer tip with N(0, ``touch_noise_mm``²) per axis; the pixel written is
the corner's true image rounded to 0.1 px (a person reading it off the annotated image).
Check points: random points of the plate's printed area, their exact pixels and robot points.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from eyetohand.core import InputError, atomic_write_bytes, atomic_write_text
from eyetohand.geometry import Camera, rodrigues_to_matrix
from eyetohand.sim.cell import Cell
from eyetohand.sim.simulate import true_camera
from eyetohand.vision import PlateSpec, charuco_board

_STEP = 8
BLACK, WHITE, BACKGROUND = 0.08, 0.85, 0.35


@dataclass(frozen=True)
class PlatePlacement:
    """Where the plate lies: plate frame → robot frame, ``X = R·P + t`` (mm)."""

    R: np.ndarray
    t_mm: np.ndarray

    def to_robot(self, plate_mm: np.ndarray) -> np.ndarray:
        return np.asarray(plate_mm, float) @ self.R.T + self.t_mm


def place_plate(
    cam: Camera, spec: PlateSpec, z_mm: float, *, yaw_deg: float = 10.0, tilt_deg: float = 0.3
) -> PlatePlacement:
    """The plate centred under the camera's view centre at height ``z_mm``, its x axis ``yaw_deg``
    from the image's u axis as projected, tilted ``tilt_deg`` about its x axis."""
    w, h = cam.image_size
    centre = cam.image_to_robot(np.array([(w - 1) / 2, (h - 1) / 2]), z_mm).reshape(3)
    u_dir = cam.image_to_robot(np.array([(w - 1) / 2 + 100, (h - 1) / 2]), z_mm).reshape(3) - centre
    a = math.atan2(u_dir[1], u_dir[0]) + math.radians(yaw_deg)
    ca, sa = math.cos(a), math.sin(a)
    # plate z points away from the camera (down), so x, y, z stay right-handed: y = z × x
    Rz = np.array([[ca, sa, 0.0], [sa, -ca, 0.0], [0.0, 0.0, -1.0]])  # columns: plate x, y, z in robot
    tilt = rodrigues_to_matrix(np.array([ca, sa, 0.0]) * math.radians(tilt_deg))
    R = tilt @ Rz
    pts = spec.points_mm()
    mid = 0.5 * (pts.min(axis=0) + pts.max(axis=0))
    return PlatePlacement(R, centre - R @ mid)


def _plate_coords(cam: Camera, pl: PlatePlacement) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Plate (x, y) mm of every pixel centre (H, W) each, and the pixel's footprint (mm) along x, y."""
    w, h = cam.image_size
    gu = np.arange(0, w + _STEP, _STEP, dtype=float)
    gv = np.arange(0, h + _STEP, _STEP, dtype=float)
    uu, vv = np.meshgrid(gu, gv)
    origin, d = cam.image_to_ray(np.column_stack([uu.ravel(), vv.ravel()]))
    n = pl.R[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = ((pl.t_mm - origin) @ n) / (d @ n)
    X = origin + s[:, None] * d
    P = ((X - pl.t_mm) @ pl.R)[:, :2].reshape(len(gv), len(gu), 2)
    # bilinear, rows then columns
    v = np.arange(h)
    iv, fv = v // _STEP, (v % _STEP / _STEP)[:, None, None]
    rows = P[iv] * (1 - fv) + P[iv + 1] * fv  # (h, gw, 2)
    u = np.arange(w)
    iu, fu = u // _STEP, (u % _STEP / _STEP)[None, :, None]
    full = rows[:, iu] * (1 - fu) + rows[:, iu + 1] * fu  # (h, w, 2)
    du = np.abs(np.gradient(P, axis=1)) / _STEP
    dv = np.abs(np.gradient(P, axis=0)) / _STEP
    foot = np.nan_to_num(du + dv, nan=1.0).reshape(-1, 2).mean(axis=0)
    return full[..., 0], full[..., 1], foot


def _edge(x: np.ndarray, w: float) -> np.ndarray:
    """Box-filtered step: −1 … +1 across an edge at 0, over a footprint ``w``."""
    return np.clip(2.0 * x / w, -1.0, 1.0)


def _pattern(spec: PlateSpec, x: np.ndarray, y: np.ndarray, foot: np.ndarray) -> np.ndarray:
    """Grey level (0..1) of the plate at plate (x, y), box-filtered; the plate's border is white."""
    p = spec.pitch_mm
    lo, hi = spec.outline_mm()
    inside_plate = (_edge(x - lo[0], foot[0]) + 1) * (_edge(hi[0] - x, foot[0]) + 1) / 4
    inside_plate *= (_edge(y - lo[1], foot[1]) + 1) * (_edge(hi[1] - y, foot[1]) + 1) / 4
    if spec.kind == "charuco":
        grey = WHITE + (_charuco(spec, x, y, foot) - 1.0) * (WHITE - BLACK)
    elif spec.kind == "chessboard":
        # the outer squares' far edges are the board's (below), not the square wave's
        xs, ys = np.clip(x, -0.5 * p, (spec.cols - 0.5) * p), np.clip(y, -0.5 * p, (spec.rows - 0.5) * p)
        kx, ky = np.rint(xs / p), np.rint(ys / p)
        gx = np.where(kx % 2 == 0, 1.0, -1.0) * _edge(xs - kx * p, foot[0])
        gy = np.where(ky % 2 == 0, 1.0, -1.0) * _edge(ys - ky * p, foot[1])
        f = gx * gy  # +1 white, −1 black
        qlo, qhi = -p, np.array([spec.cols * p, spec.rows * p])
        board = (_edge(x - qlo, foot[0]) + 1) * (_edge(qhi[0] - x, foot[0]) + 1) / 4
        board *= (_edge(y - qlo, foot[1]) + 1) * (_edge(qhi[1] - y, foot[1]) + 1) / 4
        grey = WHITE + board * (0.5 * (1 - f)) * (BLACK - WHITE)
    else:
        radius = (0.3 if spec.kind == "circles" else 0.35) * p
        d = np.full_like(x, np.inf)
        ry = np.floor(y / p)
        for r in (np.clip(ry, 0, spec.rows - 1), np.clip(ry + 1, 0, spec.rows - 1)):
            odd = r % 2 if spec.kind == "acircles" else 0.0
            step = 2.0 if spec.kind == "acircles" else 1.0
            c = np.clip(np.rint((x / p - odd) / step), 0, spec.cols - 1)
            d = np.minimum(d, np.hypot(x - (step * c + odd) * p, y - r * p))
        cover = np.clip((radius - d) / float(foot.mean()) + 0.5, 0.0, 1.0)
        grey = WHITE + cover * (BLACK - WHITE)
    return BACKGROUND + inside_plate * (grey - BACKGROUND)


def _charuco(spec: PlateSpec, x: np.ndarray, y: np.ndarray, foot: np.ndarray) -> np.ndarray:
    """OpenCV's image of the ChArUco board (1 white, 0 black) at plate (x, y): drawn at 4 samples per
    pixel footprint (at most 20 per mm), blurred over the footprint, sampled bilinearly; 1 off the board."""
    import cv2

    p = spec.pitch_mm
    ppm = float(min(4.0 / max(float(foot.mean()), 1e-3), 20.0))
    w, h = round((spec.cols + 1) * p * ppm), round((spec.rows + 1) * p * ppm)
    board = charuco_board(spec).generateImage((w, h), marginSize=0, borderBits=1).astype(np.float32) / 255
    board = cv2.GaussianBlur(board, (0, 0), 0.3 * float(foot.mean()) * ppm)
    bx = ((x + p) * w / ((spec.cols + 1) * p) - 0.5).astype(np.float32)
    by = ((y + p) * h / ((spec.rows + 1) * p) - 0.5).astype(np.float32)
    return cv2.remap(board, bx, by, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=1.0)


def render_plate(
    cam: Camera, spec: PlateSpec, placement: PlatePlacement, *, blur_px=1.0, noise=0.01, rng=0, bits=8
) -> np.ndarray:
    """The plate's image (h, w) uint8 through ``cam`` (see the module docstring)."""
    import cv2

    rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    x, y, foot = _plate_coords(cam, placement)
    img: np.ndarray = _pattern(spec, x, y, foot).astype(np.float32)
    img[~np.isfinite(img)] = BACKGROUND
    if blur_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_px)
    top = 255 if bits == 8 else 65535
    img *= np.float32(top)
    if noise > 0:
        img += np.float32(noise * top) * rng.standard_normal(img.shape, dtype=np.float32)
    return np.clip(np.rint(img), 0, top).astype(np.uint8 if bits == 8 else np.uint16)


@dataclass(frozen=True)
class PlateSimulation:
    """A simulated plate session: the image, the touches and check points, and the truth."""

    cell: Cell
    spec: PlateSpec
    camera: Camera
    placement: PlatePlacement
    image: np.ndarray | None
    touches_csv: str
    check_csv: str
    true_uv_px: np.ndarray  # every plate point's exact pixel
    touched: tuple[int, ...]


def simulate_plate(
    cell: Cell | None = None,
    spec: PlateSpec | str = "chessboard:9x6:15",
    *,
    n_touches: int = 4,
    touch_noise_mm: float = 0.05,
    z_mm: float | None = None,
    yaw_deg: float = 10.0,
    tilt_deg: float = 0.3,
    n_check: int = 20,
    seed: int | None = None,
    render: bool = True,
    shift_mm: tuple[float, float] = (0.0, 0.0),
    cover_px: tuple[float, float, float, float] | None = None,
) -> PlateSimulation:
    """One plate image in ``cell``, ``n_touches`` (3..4) touches of its corners A–D, ``n_check``
    check points on the plate (module docstring). ``render`` False: no image (``image`` None; the
    studies that need only the truth).

    A plate seen in part (a ChArUco board's use): ``shift_mm`` moves the plate along its own x, y from
    the view's centre (part of it may leave the image), ``cover_px`` (u0, v0, u1, v1) blanks a rectangle
    of the image (something lying on the plate). Then the corners A–D touched are the extreme ones of
    those *visible* (:meth:`~eyetohand.vision.plate.PlateSpec.corner_labels`): the corner and the four
    squares around it in the image, 2 px from its edges, clear of the cover; the check points are
    visible points of the plate."""
    cell = Cell.default() if cell is None else cell
    spec = PlateSpec.parse(spec) if isinstance(spec, str) else spec
    if n_touches not in (3, 4):
        raise InputError(f"touches: expected 3 or 4 (the plate's corners A-D), got {n_touches!r}")
    if not (math.isfinite(touch_noise_mm) and touch_noise_mm >= 0):
        raise InputError(f"touch noise: expected a number of mm >= 0, got {touch_noise_mm!r}")
    if len(shift_mm) != 2 or not all(math.isfinite(float(c)) for c in shift_mm):
        raise InputError(f"plate shift: expected 2 finite numbers of mm (dx, dy), got {tuple(shift_mm)!r}")
    if cover_px is not None and (
        len(cover_px) != 4
        or not all(math.isfinite(float(c)) for c in cover_px)
        or not (cover_px[0] < cover_px[2] and cover_px[1] < cover_px[3])
    ):
        raise InputError(
            "plate cover: expected a rectangle u0,v0,u1,v1 px with u0 < u1 and v0 < v1, "
            f"got {tuple(cover_px)!r}"
        )
    cam = true_camera(cell)
    z = float(cell.values["belt"]["z_mm"]) if z_mm is None else float(z_mm)
    pl = place_plate(cam, spec, z, yaw_deg=yaw_deg, tilt_deg=tilt_deg)
    in_part = cover_px is not None or tuple(shift_mm) != (0.0, 0.0)
    if in_part:
        pl = PlatePlacement(pl.R, pl.t_mm + pl.R @ np.array([shift_mm[0], shift_mm[1], 0.0], float))
    world = pl.to_robot(spec.points_mm())
    uv = cam.robot_to_image(world)
    lo, hi = spec.outline_mm()
    outline = np.array([[lo[0], lo[1], 0], [hi[0], lo[1], 0], [hi[0], hi[1], 0], [lo[0], hi[1], 0]])
    if not in_part and not cam.in_image(cam.robot_to_image(pl.to_robot(outline)), 2.0).all():
        raise InputError(
            f"plate {spec.text} does not fit in the camera's view at z = {z:g} mm: choose a smaller "
            "pitch or fewer points"
        )

    def visible(plate_xy: np.ndarray) -> np.ndarray:
        """(..., 2) plate points → (...) bool: in the image 2 px from its edges, clear of the cover."""
        p3 = np.concatenate([plate_xy, np.zeros(plate_xy.shape[:-1] + (1,))], axis=-1).reshape(-1, 3)
        px = cam.robot_to_image(pl.to_robot(p3))
        ok = np.asarray(cam.in_image(px, 2.0), bool)
        if cover_px is not None:
            u0, v0, u1, v1 = cover_px
            ok &= ~((px[:, 0] >= u0 - 2) & (px[:, 0] <= u1 + 2) & (px[:, 1] >= v0 - 2) & (px[:, 1] <= v1 + 2))
        return ok.reshape(plate_xy.shape[:-1])

    around = np.stack(np.meshgrid(*[np.linspace(-1, 1, 5)] * 2), axis=-1).reshape(-1, 2) * spec.pitch_mm
    seen = np.asarray(visible(spec.points_mm()[:, None, :2] + around[None]).all(axis=1), bool)
    if seen.sum() < 3:
        raise InputError(
            f"plate {spec.text}: only {int(seen.sum())} of its corners in view, clear of the cover"
        )
    ss = np.random.SeedSequence(seed)
    rng_img, rng_touch, rng_check = (np.random.default_rng(s) for s in ss.spawn(3))
    r = cell.values["render"]
    image = (
        render_plate(cam, spec, pl, blur_px=r["blur_px"], noise=r["noise"], rng=rng_img) if render else None
    )
    if image is not None and cover_px is not None:
        u0, v0, u1, v1 = (max(0, round(c)) for c in cover_px)
        image[v0 : v1 + 1, u0 : u1 + 1] = round(BACKGROUND * (255 if image.dtype == np.uint8 else 65535))
    labels = list(spec.corner_labels(seen).items())[:n_touches]
    idx = tuple(i for _, i in labels)
    xyz = world[list(idx)] + rng_touch.normal(0.0, touch_noise_mm, (len(idx), 3))
    rows = ["u,v,x,y,z,id"] + [
        f"{uv[i, 0]:.1f},{uv[i, 1]:.1f},{p[0]:.3f},{p[1]:.3f},{p[2]:.3f},{lab}"
        for (lab, i), p in zip(labels, xyz, strict=True)
    ]
    pts = spec.points_mm()
    q = pts.min(axis=0) + rng_check.random((n_check * (20 if in_part else 1), 3)) * (
        pts.max(axis=0) - pts.min(axis=0)
    )
    q[:, 2] = 0.0
    if in_part:  # the check points among the corners seen: in a square whose 4 corners are in view
        cx = np.clip(np.floor(q[:, 0] / spec.pitch_mm), 0, spec.cols - 2).astype(int)
        cy = np.clip(np.floor(q[:, 1] / spec.pitch_mm), 0, spec.rows - 2).astype(int)
        k = cy * spec.cols + cx
        q = q[seen[k] & seen[k + 1] & seen[k + spec.cols] & seen[k + spec.cols + 1]][:n_check]
    cw = pl.to_robot(q)
    cuv = cam.robot_to_image(cw)
    check = ["u,v,x,y,z,id"] + [
        f"{a[0]:.6f},{a[1]:.6f},{b[0]:.6f},{b[1]:.6f},{b[2]:.6f},c{k + 1}"
        for k, (a, b) in enumerate(zip(cuv, cw, strict=True))
    ]
    return PlateSimulation(
        cell, spec, cam, pl, image, "\n".join(rows) + "\n", "\n".join(check) + "\n", uv, idx
    )


def write_plate_simulation(sim: PlateSimulation, out_dir: str | os.PathLike) -> list[Path]:
    """``plate.png``, ``touches.csv``, ``check.csv`` in ``out_dir`` (created), written atomically."""
    import cv2

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if sim.image is None:
        raise InputError("this plate simulation was made without its image (render=False)")
    ok, png = cv2.imencode(".png", sim.image)
    if not ok:
        raise InputError(f"{out / 'plate.png'}: could not encode the image")
    return [
        atomic_write_bytes(out / "plate.png", png.tobytes()),
        atomic_write_text(out / "touches.csv", sim.touches_csv),
        atomic_write_text(out / "check.csv", sim.check_csv),
    ]


__all__ = [
    "PlatePlacement",
    "PlateSimulation",
    "place_plate",
    "render_plate",
    "simulate_plate",
    "write_plate_simulation",
]
