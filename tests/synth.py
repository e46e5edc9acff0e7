"""Synthetic point pairs from an independent camera model (OpenCV's projectPoints).

A camera above the robot's plane, looking down with a tilt; robot points on a grid at one or more
heights; image points projected with OpenCV (optionally with lens distortion) plus Gaussian pixel noise.
"""

from __future__ import annotations

import cv2
import numpy as np

from eyetohand.core.pairs import PointPairs


def make_camera(
    tilt_deg=8.0, height_mm=450.0, f_px=2600.0, size=(2448, 2048), dist=None, seed=0, pp_offset_px=(6.0, -4.0)
):
    rng = np.random.default_rng(seed)
    w, h = size
    du, dv = pp_offset_px
    K = np.array([[f_px, 0, (w - 1) / 2 + du], [0, f_px, (h - 1) / 2 + dv], [0, 0, 1.0]])
    # camera looking down (-z of the robot) with a small tilt about a random horizontal axis
    axis = rng.normal(size=2)
    axis /= np.linalg.norm(axis)
    R_down = np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])
    R_tilt, _ = cv2.Rodrigues(np.r_[axis, 0.0] * np.deg2rad(tilt_deg))
    R = R_tilt @ R_down
    centre = np.array([20.0, 600.0, height_mm])  # camera position in robot mm
    t = -R @ centre
    rvec, _ = cv2.Rodrigues(R)
    d = np.zeros(5) if dist is None else np.asarray(dist, float)
    return {"K": K, "dist": d, "rvec": rvec.ravel(), "tvec": t, "size": size, "centre": centre}


def project(cam, xyz_mm):
    uv, _ = cv2.projectPoints(
        np.asarray(xyz_mm, float).reshape(-1, 1, 3), cam["rvec"], cam["tvec"], cam["K"], cam["dist"]
    )
    return uv.reshape(-1, 2)


def grid_pairs(cam, n_side=5, heights=(0.0,), span_mm=120.0, noise_px=0.0, seed=1, jitter_mm=0.0):
    """Robot grid points (n_side × n_side per height) under the camera, with projected image points."""
    rng = np.random.default_rng(seed)
    g = np.linspace(-span_mm / 2, span_mm / 2, n_side)
    xx, yy = np.meshgrid(g, g)
    pts = []
    for z in heights:
        xy = np.c_[xx.ravel(), yy.ravel()] + cam["centre"][:2]
        xy = xy + rng.normal(scale=jitter_mm, size=xy.shape) if jitter_mm else xy
        pts.append(np.c_[xy, np.full(len(xy), z)])
    xyz = np.vstack(pts)
    uv = project(cam, xyz) + rng.normal(scale=noise_px, size=(len(xyz), 2))
    return PointPairs.from_arrays(uv, xyz)


def random_pairs(cam, n, heights=(0.0,), span_mm=120.0, noise_px=0.0, seed=2):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-span_mm / 2, span_mm / 2, size=(n, 2)) + cam["centre"][:2]
    z = rng.choice(np.asarray(heights, float), size=n)
    xyz = np.c_[xy, z]
    uv = project(cam, xyz) + rng.normal(scale=noise_px, size=(n, 2))
    return PointPairs.from_arrays(uv, xyz)


def limit_view(tilt_deg: float, distance_mm: float = 800.0, size=(1920, 1200), focal_px: float = 2400.0):
    """The limit cell's camera (docs/limit.md; benchmarks/bias.py, tests/test_circles.py): no lens, the
    principal point at the image centre, its axis ``tilt_deg`` from the plane's normal, meeting the plane
    z = 0 ``distance_mm`` away along the axis."""
    from eyetohand.geometry import Camera

    t = np.deg2rad(tilt_deg)
    return Camera.looking_down(
        size,
        focal_px=focal_px,
        height_mm=distance_mm * np.cos(t),
        tilt_deg=tilt_deg,
        tilt_direction_deg=90.0,
        yaw_deg=0.0,
        dist=(0.0, 0.0, 0.0, 0.0, 0.0),
        pp_offset_px=(0.0, 0.0),
    )


def plane_grid(cam, n: int, lo: float, hi: float) -> np.ndarray:
    """(n², 3) plane points (z = 0) under an n×n grid of pixels spanning lo..hi of ``cam``'s image."""
    w, h = cam.image_size
    uu, vv = np.meshgrid(np.linspace(lo * w, hi * w, n), np.linspace(lo * h, hi * h, n))
    return cam.image_to_robot(np.column_stack([uu.ravel(), vv.ravel()]), 0.0)


def detect_rendered(cam, xyz_mm: np.ndarray, diameter_mm: float, rng) -> np.ndarray:
    """(N, 2) centres ``detect_target`` finds of the circle target rendered at each point, each in a
    window around it (``cam`` with its principal point moved by the window's corner) — the detector's
    answer on a picture of the cell (tests/test_circles.py, benchmarks/bias.py)."""
    from eyetohand import detect_target
    from eyetohand.geometry import Camera
    from eyetohand.vision.render import Target, circle_truth, render

    target = Target(diameter_mm, strip_width_mm=diameter_mm + 6, strip_length_mm=3 * diameter_mm + 10)
    out = np.empty((len(xyz_mm), 2))
    for i, X in enumerate(xyz_mm):
        tr = circle_truth(cam, X, diameter_mm)
        half = int(np.ceil(1.2 * max(tr.axes_px) + 10))
        x0, y0 = int(round(tr.centre_px[0])) - half, int(round(tr.centre_px[1])) - half
        K = cam.K.copy()
        K[0, 2] -= x0
        K[1, 2] -= y0
        window = Camera.from_opencv(K, cam.dist, cam.R, cam.t, (2 * half, 2 * half))
        img, _ = render(window, X, target=target, vignetting=0, rng=rng)
        det = detect_target(img, polarity="dark", diameter_px=tr.diameter_px)
        if not det.ok:
            raise RuntimeError(f"target at {X} not found: {det.reason}")
        out[i] = det.u + x0, det.v + y0
    return out
