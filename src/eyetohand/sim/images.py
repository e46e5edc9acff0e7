"""Images of the simulated sessions: the target seen by the cell's hidden camera.

Each image is rendered exactly through the hidden camera: every pixel centre is cast back (lens
distortion included) onto the target's plane z, and shaded by what lies there — a dark solid circle
(``target.diameter_mm``) on a bright metal strip (``strip_width_mm`` × ``strip_length_mm``, along the
tool's x axis, turning with the tool angle) over a textured belt fixed in the robot frame. Edges are
anti-aliased over one pixel's footprint; then Gaussian blur (``render.blur_px``), vignetting
(``render.vignetting``) and noise (``render.noise``, seeded). 8-bit PNG.

The true centre of each image is in ``truth.json`` (the projection of the circle's centre); a
detector's centroid of the projected disc differs from it by the perspective bias of a tilted view,
hundredths of a pixel with the default cell.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..io import atomic_write_bytes, atomic_write_text
from ..tcp_offset import rotations

BELT_LEVEL = 0.35
STRIP_LEVEL = 0.85
CIRCLE_LEVEL = 0.08


class _Rays:
    """Rays of every pixel centre of the hidden camera, in the robot frame (computed once)."""

    def __init__(self, camera):
        import cv2

        w, h = camera.image_size
        uu, vv = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
        uv = np.stack([uu.ravel(), vv.ravel()], axis=1)
        n = cv2.undistortPoints(uv.reshape(-1, 1, 2), camera.K, camera.dist,
                                criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12))
        ray = np.column_stack([n.reshape(-1, 2), np.ones(len(uv))]) @ camera.R
        self.shape = (h, w)
        self.centre = -camera.R.T @ camera.t
        self.ray = ray  # (H*W, 3), unnormalised: ray[:, 2] < 0 looking down
        self.f = float(camera.K[0, 0])

    def on_plane(self, z_mm: float):
        """Plane points (H*W, 2) and the size of a pixel there (H*W,) in mm."""
        s = (z_mm - self.centre[2]) / self.ray[:, 2]
        xy = self.centre[:2] + s[:, None] * self.ray[:, :2]
        mm_per_px = s * np.linalg.norm(self.ray, axis=1) / self.f
        return xy, mm_per_px


def _coverage(signed_mm: np.ndarray, mm_per_px: np.ndarray) -> np.ndarray:
    """Fraction of a pixel inside a shape from the signed distance to its edge (inside < 0)."""
    return np.clip(0.5 - signed_mm / mm_per_px, 0.0, 1.0)


def _belt(xy: np.ndarray, rng_phase: np.ndarray) -> np.ndarray:
    """A belt texture fixed in the robot frame: a few weak sinusoids of the plane coordinates."""
    k = np.array([[0.9, 0.4], [-0.3, 1.3], [2.1, -1.7], [0.15, 0.05]])
    amp = np.array([0.03, 0.025, 0.015, 0.04])
    t = xy @ k.T + rng_phase
    return BELT_LEVEL + (amp * np.sin(t)).sum(axis=1)


def render_target(rays: _Rays, cell, centre_mm, angle_deg: float, rng: np.random.Generator) -> np.ndarray:
    """One 8-bit image of the target whose circle's centre is at ``centre_mm`` (x, y, z)."""
    import cv2

    tgt = cell.values["target"]
    rnd = cell.values["render"]
    xy, px_mm = rays.on_plane(float(centre_mm[2]))
    local = (xy - np.asarray(centre_mm[:2], float)) @ rotations(np.array([angle_deg]))[0]  # tool frame
    img = _belt(xy, np.array([0.3, 1.1, 2.0, 0.7]))
    if tgt["strip_width_mm"] > 0 and tgt["strip_length_mm"] > 0:
        half = np.array([tgt["strip_length_mm"], tgt["strip_width_mm"]]) / 2
        q = np.abs(local) - half
        signed = np.where((q > 0).any(axis=1), np.linalg.norm(np.maximum(q, 0), axis=1), q.max(axis=1))
        img = img + (STRIP_LEVEL - img) * _coverage(signed, px_mm)
    signed = np.linalg.norm(local, axis=1) - tgt["diameter_mm"] / 2
    img = img + (CIRCLE_LEVEL - img) * _coverage(signed, px_mm)
    img = img.reshape(rays.shape)
    if rnd["blur_px"] > 0:
        img = cv2.GaussianBlur(img, (0, 0), rnd["blur_px"])
    if rnd["vignetting"] > 0:
        h, w = rays.shape
        yy, xx = np.mgrid[0:h, 0:w]
        r2 = ((xx - (w - 1) / 2) ** 2 + (yy - (h - 1) / 2) ** 2) / (((w - 1) / 2) ** 2 + ((h - 1) / 2) ** 2)
        img = img * (1 - rnd["vignetting"] * r2)
    if rnd["noise"] > 0:
        img = img + rng.normal(0.0, rnd["noise"], img.shape)
    return np.clip(np.rint(img * 255), 0, 255).astype(np.uint8)


def write_images(sim, out: Path) -> list[Path]:
    """Render every pair and check point of ``sim`` into ``out/images``, with ``poses.csv`` (the pairs'
    robot coordinates) and ``check_poses.csv`` (the check points' true coordinates)."""
    import cv2

    from .simulate import poses_csv

    rays = _Rays(sim.camera)
    rng = np.random.default_rng(np.random.SeedSequence(sim.seed).spawn(5)[4])
    written: list[Path] = []
    angles = sim.pairs.angle_deg if sim.pairs.angle_deg is not None else np.zeros(len(sim.pairs))
    names = []
    for i, pid in enumerate(sim.pairs.ids):
        name = f"images/pair_{pid}.png"
        img = render_target(rays, sim.cell, sim.target_mm[i], float(angles[i]), rng)
        written.append(atomic_write_bytes(out / name, cv2.imencode(".png", img)[1].tobytes()))
        names.append(name)
    written.append(atomic_write_text(out / "poses.csv", poses_csv(names, sim.pairs.xyz_mm,
                                                                  sim.pairs.angle_deg)))
    if sim.check is not None:
        A = sim.cell.axis_matrix
        names = []
        for i, pid in enumerate(sim.check.ids):
            name = f"images/check_{pid}.png"
            phys = sim.check.xyz_mm[i].copy()
            phys[:2] = A @ phys[:2]
            img = render_target(rays, sim.cell, phys, 0.0, rng)
            written.append(atomic_write_bytes(out / name, cv2.imencode(".png", img)[1].tobytes()))
            names.append(name)
        written.append(atomic_write_text(out / "check_poses.csv", poses_csv(names, sim.check.xyz_mm)))
    return written
