"""Parts on the table: the virtual cell's scene for a pick loop (``LOCATE``, docs/collection.md).

:class:`PartsTable` lays ``n`` round parts (dark discs of ``diameter_mm``) at seeded random places on
the plane z = ``z_mm`` (a table top), anywhere the hidden camera sees them whole — so some lie
outside a calibration's region, as on a real table — never overlapping; it renders what the camera
sees (the project's renderer draws the table's texture, the discs are painted by exact area coverage
on their edge pixels, then the cell's blur, vignetting and image noise) and takes a part away when
the robot's gripper lands on it (:meth:`PartsTable.pick`).

Truth is where the robot must be **commanded** to put its tool on a part: the robot really goes to
``A·c + o`` for a command ``c`` at tool angle 0 (A the cell's hidden axis errors, o its hidden tool
offset, as :mod:`eyetohand.sim.camera_sim`), so a pick at ``c`` lands ``A·c + o − P`` from the part's
centre P; that is what :meth:`PartsTable.pick` answers.

The ``sim:`` camera (:class:`eyetohand.sim.SimSource`) shows this scene after ``place_parts`` and the
robot's target again after the next ``set_robot_pose`` (a collection); ``eyetohand serve --camera
sim:…`` offers the line command ``SIM`` (:func:`sim_command`): ``SIM PARTS n[,seed[,diameter[,z]]]``
→ ``OK <n placed>``; ``SIM PICK x,y`` → ``OK <dx>,<dy>,<miss>`` (mm, the landing minus the part's
centre, and its length) or ``ERR nothing to pick at x,y: …``; ``SIM LEFT`` → ``OK <parts left>``;
``SIM PLATE spec[,seed[,z_mm[,tilt_deg]]]`` → ``OK <points>``: a calibration plate lies under the camera
(``CAL PLATE``).
A simulator's command only: a real cell has gravity and a gripper for this.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from eyetohand.cell import CommandError, ascii_reason, line_count, line_numbers
from eyetohand.core import InputError
from eyetohand.vision import Target, render

CIRCLE_LEVEL = 0.08  # the renderer's dark disc (fraction of full scale)
SUPERSAMPLE = 8  # edge pixels: 8 x 8 points each
MAX_PARTS = 64
PLACE_TRIES = 200  # random places tried per part before giving up on a crowded table


@dataclass(frozen=True)
class Part:
    """One part: the centre of its top face (robot frame, mm), its diameter, and the robot command
    (x, y) that puts the tool's centre on it (tool angle 0)."""

    xyz_mm: tuple[float, float, float]
    diameter_mm: float
    command_xy_mm: tuple[float, float]


class PartsTable:
    """The parts on the table under ``camera`` (the cell's hidden one) of ``cell``."""

    def __init__(self, cell, camera):
        self.cell = cell
        self.camera = camera
        self.parts: list[Part] = []
        self.z_mm = float(cell.values["belt"]["z_mm"])
        self._base: tuple[float, np.ndarray] | None = None  # (z, noise-free table image)

    # ---------------------------------------------------------------- placing and picking
    def place(
        self, n: int, seed: int = 0, diameter_mm: float = 10.0, z_mm: float | None = None
    ) -> list[Part]:
        """Replace the parts by ``n`` new ones (seeded): centres uniform over the image (the whole
        disc at least 4 px inside it), at least 1.5 diameters apart."""
        if not 0 <= n <= MAX_PARTS:
            raise InputError(f"parts: expected 0..{MAX_PARTS}, got {n}")
        if not (math.isfinite(diameter_mm) and diameter_mm > 0):
            raise InputError(f"part diameter: expected a positive number of mm, got {diameter_mm!r}")
        z = self.z_mm if z_mm is None else float(z_mm)
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), 7]))
        w, h = self.camera.image_size
        A = self.cell.axis_matrix
        o = np.asarray(self.cell.values["robot"]["tcp_offset_mm"], float)
        parts: list[Part] = []
        for _ in range(n):
            for _ in range(PLACE_TRIES):
                uv = rng.uniform([0, 0], [w - 1, h - 1])
                c = self.camera.image_to_robot(uv[None], z)[0]
                if not np.isfinite(c).all() or not self._seen_whole(c, diameter_mm):
                    continue
                gap = [math.dist(c[:2], p.xyz_mm[:2]) / max(diameter_mm, p.diameter_mm) for p in parts]
                if min(gap, default=2.0) >= 1.5:
                    cmd = np.linalg.solve(A, c[:2] - o)
                    xyz = (float(c[0]), float(c[1]), float(c[2]))
                    parts.append(Part(xyz, float(diameter_mm), (float(cmd[0]), float(cmd[1]))))
                    break
            else:
                raise InputError(f"parts: {n} parts of {diameter_mm:g} mm do not fit apart on the table")
        self.parts = parts
        return list(parts)

    def _seen_whole(self, centre, diameter_mm: float) -> bool:
        t = np.linspace(0, 2 * math.pi, 24, endpoint=False)
        ring = centre + 0.5 * diameter_mm * np.column_stack([np.cos(t), np.sin(t), np.zeros_like(t)])
        uv = self.camera.robot_to_image(ring)
        return bool(np.isfinite(uv).all() and self.camera.in_image(uv, 4.0).all())

    def pick(self, x_mm: float, y_mm: float) -> tuple[Part, float, float] | None:
        """The robot closes its gripper commanded at (x, y) (tool angle 0): the part it lands on
        (its centre within the part's radius) is taken away → (part, dx, dy) mm, the landing minus the
        part's centre; None when it lands on none."""
        land = self.cell.axis_matrix @ np.array([x_mm, y_mm]) + np.asarray(
            self.cell.values["robot"]["tcp_offset_mm"], float
        )
        best = None
        for k, p in enumerate(self.parts):
            d = math.dist(land, p.xyz_mm[:2])
            if d <= 0.5 * p.diameter_mm and (best is None or d < best[1]):
                best = (k, d)
        if best is None:
            return None
        part = self.parts.pop(best[0])
        return part, float(land[0] - part.xyz_mm[0]), float(land[1] - part.xyz_mm[1])

    def nearest_mm(self, x_mm: float, y_mm: float) -> float | None:
        land = self.cell.axis_matrix @ np.array([x_mm, y_mm])
        return min((math.dist(land, p.xyz_mm[:2]) for p in self.parts), default=None)

    # ---------------------------------------------------------------- the image
    def render(self, rng: np.random.Generator) -> np.ndarray:
        """What the camera sees now: the table with the parts, 8-bit grey (h, w)."""
        import cv2

        z = self.parts[0].xyz_mm[2] if self.parts else self.z_mm
        img = self._table(z).copy()
        for p in self.parts:
            self._paint(img, p)
        rnd = self.cell.values["render"]
        if rnd["blur_px"] > 0:
            img = cv2.GaussianBlur(img, (0, 0), rnd["blur_px"])
        h, w = img.shape
        if rnd["vignetting"] > 0:
            rx = ((np.arange(w, dtype=np.float32) - (w - 1) / 2) ** 2)[None, :]
            ry = ((np.arange(h, dtype=np.float32) - (h - 1) / 2) ** 2)[:, None]
            img *= 1 - np.float32(rnd["vignetting"] / (((w - 1) / 2) ** 2 + ((h - 1) / 2) ** 2)) * (rx + ry)
        img *= np.float32(255)
        if rnd["noise"] > 0:
            img += np.float32(rnd["noise"] * 255) * rng.standard_normal((h, w), dtype=np.float32)
        return np.clip(np.rint(img), 0, 255).astype(np.uint8)

    def _table(self, z: float) -> np.ndarray:
        """The bare table top at height z (the renderer's texture), noise-free, float32 in 0..1."""
        if self._base is None or self._base[0] != z:
            far = np.array([*(np.asarray(self.cell.values["camera"]["look_at_mm"]) + 1e5), z])
            target = Target(diameter_mm=1.0, strip_width_mm=0.0, strip_length_mm=0.0)
            img, _ = render(self.camera, far, target=target, blur_px=0, noise=0, vignetting=0, bits=16)
            self._base = (z, (img.astype(np.float32) / 65535).astype(np.float32))
        return self._base[1]

    def _paint(self, img: np.ndarray, part: Part) -> None:
        """Darken the pixels the disc covers by their covered area (exact to 1/64 on edge pixels)."""
        c = np.asarray(part.xyz_mm, float)
        r = 0.5 * part.diameter_mm
        t = np.linspace(0, 2 * math.pi, 48, endpoint=False)
        ring = c + r * np.column_stack([np.cos(t), np.sin(t), np.zeros_like(t)])
        uv = self.camera.robot_to_image(ring)
        h, w = img.shape
        x0, y0 = (max(int(math.floor(v)) - 3, 0) for v in uv.min(axis=0))
        x1, y1 = (int(math.ceil(v)) + 4 for v in uv.max(axis=0))
        x1, y1 = min(x1, w), min(y1, h)
        us, vs = np.meshgrid(np.arange(x0, x1, dtype=float), np.arange(y0, y1, dtype=float))
        pix = np.column_stack([us.ravel(), vs.ravel()])
        xy = self.camera.image_to_robot(pix, c[2])[:, :2]
        d = np.hypot(*(xy - c[:2]).T) - r
        foot = float(np.median(np.hypot(*np.diff(xy.reshape(us.shape + (2,)), axis=1).reshape(-1, 2).T)))
        cov = (d <= -foot).astype(float)
        edge = np.abs(d) < foot
        if edge.any():
            s = (np.arange(SUPERSAMPLE) + 0.5) / SUPERSAMPLE - 0.5
            off = np.array([(a, b) for b in s for a in s])
            pts = (pix[edge][:, None, :] + off[None]).reshape(-1, 2)
            sub = self.camera.image_to_robot(pts, c[2])[:, :2]
            inside = (np.hypot(*(sub - c[:2]).T) <= r).reshape(-1, len(off))
            cov[edge] = inside.mean(axis=1)
        roi = img[y0:y1, x0:x1]
        roi += (np.float32(CIRCLE_LEVEL) - roi) * cov.reshape(us.shape).astype(np.float32)


# ---------------------------------------------------------------- the SIM line command

SIM_USAGE = (
    "expected SIM PARTS n[,seed[,diameter_mm[,z_mm]]], SIM PICK x,y, SIM LEFT or "
    "SIM PLATE spec[,seed[,z_mm[,tilt_deg]]]"
)


def sim_command(source, line: str) -> str:
    """One ``SIM …`` line for the ``sim:`` camera ``source`` → its reply (module docstring)."""
    words = line.strip().split(None, 2)
    cmd = words[1].upper() if len(words) > 1 else ""
    args = [a.strip() for a in words[2].split(",")] if len(words) > 2 else []
    try:
        if cmd == "PARTS" and 1 <= len(args) <= 4:
            vals = line_numbers(args, ("n", "seed", "diameter_mm", "z_mm"), "SIM PARTS")
            n, seed = line_count(vals[0]), line_count(vals[1]) if len(vals) > 1 else 0
            if not isinstance(n, int) or not isinstance(seed, int):
                raise CommandError("SIM PARTS: n and seed must be whole numbers")
            placed = source.place_parts(
                n, seed, vals[2] if len(vals) > 2 else 10.0, vals[3] if len(vals) > 3 else None
            )
            return f"OK {len(placed)}"
        if cmd == "PICK" and len(args) == 2:
            x, y = line_numbers(args, ("x", "y"), "SIM PICK", "mm")
            got = source.pick(x, y)
            if got is None:
                near = source.parts_table.nearest_mm(x, y)
                why = "no parts left" if near is None else f"the nearest part's centre is {near:.3f} mm away"
                return f"ERR nothing to pick at {x:.3f},{y:.3f}: {why}"
            _, dx, dy = got
            return f"OK {dx:.4f},{dy:.4f},{math.hypot(dx, dy):.4f}"
        if cmd == "PLATE" and 1 <= len(args) <= 4:
            vals = line_numbers(args[1:], ("seed", "z_mm", "tilt_deg"), "SIM PLATE")
            seed = line_count(vals[0]) if vals else 0
            if not isinstance(seed, int):
                raise CommandError("SIM PLATE: seed must be a whole number")
            z = vals[1] if len(vals) > 1 else None
            tilt = vals[2] if len(vals) > 2 else 0.3
            return f"OK {source.show_plate(args[0], seed, z, tilt)}"
        if cmd == "LEFT" and not args:
            return f"OK {len(source.parts_table.parts)}"
        raise CommandError(SIM_USAGE)
    except CommandError as exc:
        return f"ERR {ascii_reason(str(exc))}"
    except InputError as exc:
        return f"ERR {ascii_reason(str(exc).splitlines()[0])}"


__all__ = ["Part", "PartsTable", "sim_command"]
