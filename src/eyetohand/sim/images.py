"""Images of the simulated sessions: the target seen by the cell's hidden camera.

Rendered by :func:`eyetohand.vision.render.render` (the project's one renderer) exactly through the hidden
camera: every pixel is cast back (lens distortion included) onto the target's plane z and shaded by
what lies there — a dark solid circle (``target.diameter_mm``) on a bright metal strip
(``strip_width_mm`` × ``strip_length_mm``, along the tool's x axis, turning with the tool angle) over a
textured belt fixed in the robot frame. Edge pixels are supersampled (exact area coverage); then
Gaussian blur (``render.blur_px``), vignetting (``render.vignetting``) and noise (``render.noise``,
seeded). 8-bit PNG.

The true centre of each image is in ``truth.json`` (the projection of the circle's centre); a
detector's centre of the imaged ellipse differs from it by the perspective bias of a tilted view,
hundredths of a pixel with the default cell.
"""

from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np

from eyetohand.core import atomic_write_bytes, atomic_write_text
from eyetohand.vision import Target, render


def poses_csv(names, xyz_mm, angle_deg=None) -> str:
    """``image,x,y,z[,angle]`` rows, the POSES.csv that ``calibrate-images`` reads."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["image", "x", "y", "z"] + (["angle"] if angle_deg is not None else []))
    for i, name in enumerate(names):
        row = [name] + [repr(float(v)) for v in xyz_mm[i]]
        if angle_deg is not None:
            row.append(repr(float(angle_deg[i])))
        w.writerow(row)
    return buf.getvalue()


def render_target(camera, cell, centre_mm, angle_deg: float, rng: np.random.Generator) -> np.ndarray:
    """One 8-bit image of the target whose circle's centre is at ``centre_mm`` (x, y, z)."""
    tgt = cell.values["target"]
    rnd = cell.values["render"]
    target = Target(tgt["diameter_mm"], tgt["strip_width_mm"], tgt["strip_length_mm"])
    img, _ = render(
        camera,
        centre_mm,
        angle_deg=angle_deg,
        target=target,
        blur_px=rnd["blur_px"],
        noise=rnd["noise"],
        vignetting=rnd["vignetting"],
        bits=8,
        rng=rng,
    )
    return img


def write_images(sim, out: Path) -> list[Path]:
    """Render every pair and check point of ``sim`` into ``out/images``, with ``poses.csv`` (the pairs'
    robot coordinates) and ``check_poses.csv`` (the check points' true coordinates)."""
    import cv2

    rng = np.random.default_rng(np.random.SeedSequence(sim.seed).spawn(5)[4])
    written: list[Path] = []
    angles = sim.pairs.angle_deg if sim.pairs.angle_deg is not None else np.zeros(len(sim.pairs))
    names = []
    for i, pid in enumerate(sim.pairs.ids):
        name = f"images/pair_{pid}.png"
        img = render_target(sim.camera, sim.cell, sim.target_mm[i], float(angles[i]), rng)
        written.append(atomic_write_bytes(out / name, cv2.imencode(".png", img)[1].tobytes()))
        names.append(name)
    written.append(
        atomic_write_text(out / "poses.csv", poses_csv(names, sim.pairs.xyz_mm, sim.pairs.angle_deg))
    )
    if sim.check is not None:
        A = sim.cell.axis_matrix
        names = []
        for i, pid in enumerate(sim.check.ids):
            name = f"images/check_{pid}.png"
            phys = sim.check.xyz_mm[i].copy()
            phys[:2] = A @ phys[:2]
            img = render_target(sim.camera, sim.cell, phys, 0.0, rng)
            written.append(atomic_write_bytes(out / name, cv2.imencode(".png", img)[1].tobytes()))
            names.append(name)
        written.append(atomic_write_text(out / "check_poses.csv", poses_csv(names, sim.check.xyz_mm)))
    return written
