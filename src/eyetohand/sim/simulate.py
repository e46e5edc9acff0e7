"""Simulate a calibration session in the virtual cell: point pairs, check points and exact truth.

What happens to a pair (all in the robot frame, mm):

1. the plan puts the target at image points over the view; at height h each is mapped to the belt
   plane's point p it shows (the hidden camera's back-projection onto z = h);
2. the robot command that brings the target there is ``c = A⁻¹·(p − Rot(θ)·o)``, rounded to 1 µm
   (A: the axes' scale and skew errors; o: the tool-centre offset; θ: the tool angle);
3. the robot really goes to ``A·c + e``, e ~ N(0, repeatability²) per axis; the target's centre is
   there plus Rot(θ)·o; the hidden camera sees it at uv; detection adds N(0, pixel_noise²) per axis;
4. the pair recorded is (noisy uv, c) — what a user would get from the robot and the detector.

Check points are random (seeded) points of the view at the check heights, with no noise: their
``u, v`` are the true image centres and ``x, y, z`` the command that puts the rotation axis on the
object (``A⁻¹·p``) — so a calibration's error on them is its own error, nothing else.

Seeds: one ``numpy.random.SeedSequence(seed)`` spawns separate streams for the layout, the robot, the
detector, the check points and the images, so e.g. asking for more check points leaves the pairs alone.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from eyetohand.cell import MAX_POINTS, Plan, is_whole_in, parse_plan
from eyetohand.core import InputError, PointPairs, atomic_write_text
from eyetohand.geometry import Camera
from eyetohand.sim.cell import Cell
from eyetohand.solve import check_seed, rotations

SCHEMA = "eyetohand.sim.truth"
COMMAND_RESOLUTION_MM = 1e-3


def true_camera(cell: Cell) -> Camera:
    """The hidden camera of a cell (OpenCV's model, as :class:`eyetohand.geometry.camera.Camera`)."""
    R, t = cell.pose
    return Camera.from_opencv(cell.K, cell.dist, R, t, cell.image_size)


@dataclass(frozen=True)
class Simulation:
    """One simulated session: the recorded ``pairs`` and ``check`` points, and the truth behind them."""

    cell: Cell
    plan: Plan
    heights_mm: tuple[float, ...]
    check_heights_mm: tuple[float, ...]
    angles_deg: tuple[float, ...] | None
    seed: int | None
    pairs: PointPairs
    check: PointPairs | None  # None without check points
    true_uv_px: np.ndarray  # noise-free image centres of the pairs
    target_mm: np.ndarray  # where the target's centre really was for each pair
    camera: Camera

    def truth(self) -> dict:
        recs = [
            {
                "id": pid,
                "u_true": float(uv[0]),
                "v_true": float(uv[1]),
                "x_target": float(p[0]),
                "y_target": float(p[1]),
                "z_target": float(p[2]),
            }
            for pid, uv, p in zip(self.pairs.ids, self.true_uv_px, self.target_mm, strict=True)
        ]
        return {
            "schema": SCHEMA,
            "cell": self.cell.to_dict(),
            "camera": self.camera.to_dict(),
            "plan": self.plan.label,
            "heights_mm": list(self.heights_mm),
            "check_heights_mm": list(self.check_heights_mm),
            "angles_deg": list(self.angles_deg) if self.angles_deg else None,
            "tcp_offset_mm": list(self.cell.values["robot"]["tcp_offset_mm"]),
            "seed": self.seed,
            "image_size": list(self.cell.image_size),
            "pairs": recs,
        }


def simulate(
    cell: Cell | None = None,
    plan: str | Plan = "grid:5x5",
    heights_mm=(150.0,),
    *,
    n_check: int = 20,
    check_heights_mm=None,
    angles_deg=None,
    seed: int | None = None,
) -> Simulation:
    """Simulate pairs for ``plan`` at each of ``heights_mm`` and ``n_check`` check points per check
    height (default: the same heights). ``angles_deg`` (A0, A1, …): every pair at tool angle A0, and
    at the first height the position nearest the view centre again at A1, … (the "9 + 2" practice
    with ``grid:3x3`` and angles 0, 90, 180); the pairs then carry an ``angle`` column."""
    cell = Cell.default() if cell is None else cell
    plan = parse_plan(plan) if isinstance(plan, str) else plan
    heights = _heights(heights_mm, "heights")
    check_heights = heights if check_heights_mm is None else _heights(check_heights_mm, "check heights")
    if not is_whole_in(n_check, 0, MAX_POINTS):
        raise InputError(
            f"check points: expected a whole number from 0 to {MAX_POINTS} per height, got {n_check!r}"
        )
    seed = check_seed(seed)
    angles = None
    if angles_deg is not None:
        angles = tuple(float(a) for a in angles_deg)
        if not angles or len(set(angles)) != len(angles) or not np.isfinite(angles).all():
            raise InputError(f"angles: expected distinct finite angles in degrees, got {angles_deg!r}")
    cam = true_camera(cell)
    _check_in_front(cell, cam, heights + check_heights)
    ss = np.random.SeedSequence(seed)
    rng_layout, rng_robot, rng_pixel, rng_check = (np.random.default_rng(s) for s in ss.spawn(4))
    A = cell.axis_matrix
    A_inv = np.linalg.inv(A)
    o = np.asarray(cell.values["robot"]["tcp_offset_mm"], float)
    margin = cell.margin_px()
    theta0 = angles[0] if angles else 0.0

    cmd_parts: list[np.ndarray] = []
    ang_parts: list[np.ndarray] = []
    for k, h in enumerate(heights):
        q = plan.layout_px(cell.image_size, margin, rng_layout)
        p = cam.image_to_robot(q, h)
        c_xy = (p[:, :2] - rotations(np.array([theta0]))[0] @ o) @ A_inv.T
        c = np.column_stack([c_xy, np.full(len(q), h)])
        c = np.round(c / COMMAND_RESOLUTION_MM) * COMMAND_RESOLUTION_MM
        cmd_parts.append(c)
        ang_parts.append(np.full(len(c), theta0))
        if angles and len(angles) > 1 and k == 0:
            centre = 0.5 * (np.array(cell.image_size, float) - 1)
            j = int(np.argmin(np.linalg.norm(q - centre, axis=1)))
            cmd_parts.append(np.repeat(c[j : j + 1], len(angles) - 1, axis=0))
            ang_parts.append(np.array(angles[1:]))
    cmd = np.vstack(cmd_parts)
    ang = np.concatenate(ang_parts)
    n = len(cmd)
    sigma_r = cell.values["robot"]["repeatability_mm"]
    actual = cmd.copy()
    actual[:, :2] = cmd[:, :2] @ A.T
    actual += rng_robot.normal(0.0, 1.0, (n, 3)) * sigma_r
    target = actual.copy()
    target[:, :2] += rotations(ang) @ o
    true_uv = cam.robot_to_image(target)
    uv = true_uv + rng_pixel.normal(0.0, 1.0, (n, 2)) * cell.values["detection"]["pixel_noise_px"]
    _check_visible(cell, true_uv, "pairs")
    ids = [str(i + 1) for i in range(n)]
    pairs = PointPairs.from_arrays(uv, cmd, ids, source="simulated pairs", angle_deg=ang if angles else None)

    chk_cmd: list[np.ndarray] = []
    chk_uv: list[np.ndarray] = []
    lo = np.array([margin, margin])
    hi = np.array(cell.image_size, float) - 1 - margin
    for h in check_heights:
        q = lo + rng_check.random((n_check, 2)) * (hi - lo)
        p = cam.image_to_robot(q, h)
        c = np.column_stack([p[:, :2] @ A_inv.T, np.full(n_check, h)])
        chk_cmd.append(c)
        chk_uv.append(cam.robot_to_image(p))
    check: PointPairs | None
    if n_check:
        check_uv = np.vstack(chk_uv)
        check = PointPairs.from_arrays(
            check_uv,
            np.vstack(chk_cmd),
            [f"c{i + 1}" for i in range(len(check_uv))],
            source="simulated check points",
        )
    else:
        check = None
    return Simulation(cell, plan, heights, check_heights, angles, seed, pairs, check, true_uv, target, cam)


def _heights(values, what: str) -> tuple[float, ...]:
    try:
        hs = tuple(float(v) for v in np.atleast_1d(values))
    except (TypeError, ValueError):
        raise InputError(f"{what}: expected numbers in mm, got {values!r}") from None
    if not hs or not np.isfinite(hs).all():
        raise InputError(f"{what}: expected finite numbers in mm, got {values!r}")
    if len(set(hs)) != len(hs):
        raise InputError(f"{what}: repeated height in {list(hs)}")
    return hs


def _check_in_front(cell: Cell, cam: Camera, heights) -> None:
    top = float(cam.position_mm[2])
    belt = cell.values["belt"]["z_mm"]
    for h in heights:
        if not (belt <= h < top - 10.0):
            raise InputError(
                f"height {h:g} mm is outside the cell: it must lie between the belt (z = {belt:g} mm) "
                f"and 10 mm below the camera (z = {top:g} mm)"
            )


def _check_visible(cell: Cell, uv: np.ndarray, what: str) -> None:
    w, h = cell.image_size
    bad = ~((uv >= 0) & (uv <= [w - 1, h - 1])).all(axis=1)
    if bad.any():
        raise InputError(
            f"{what}: {int(bad.sum())} simulated target(s) fall outside the {w}x{h} image; "
            "raise plan.margin or lower the robot's errors in the cell config"
        )


# ---------------------------------------------------------------- files


def write_simulation(sim: Simulation, out_dir: str | os.PathLike, *, images: bool = False) -> list[Path]:
    """Write ``pairs.csv``, ``check.csv``, ``truth.json`` (and with ``images`` the rendered images,
    ``poses.csv`` and ``check_poses.csv``) into ``out_dir``, each atomically."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: exists and is not a folder")
    written = [atomic_write_text(out / "pairs.csv", sim.pairs.to_csv_text())]
    if sim.check is not None:
        written.append(atomic_write_text(out / "check.csv", sim.check.to_csv_text()))
    written.append(atomic_write_text(out / "truth.json", json.dumps(sim.truth(), indent=2) + "\n"))
    if images:
        from eyetohand.sim.images import write_images

        written += write_images(sim, out)
    return written
