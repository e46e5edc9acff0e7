"""Touches of a calibration plate: the robot's readings of a few of its corners, read, snapped to the
detected corners, and turned into the plate's placement in the robot frame — or refused, each reason
in its own words.

A touches file is CSV ``[image,]u,v,x,y,z[,id]``: the pixel where the touched corner is seen (read
off the annotated image), the robot's reading of the pointer tip (mm), optionally which image
(its file name or its number, 1-based; may be left out for one image) and a name. Each touch is
snapped to the nearest detected corner; none within ``SNAP_MAX_PX`` (10 px; or ``SNAP_FRACTION`` of
the corner spacing when that is less) is refused naming the touch. Per placement (image) at least 3
touches, not on one line, each on its own corner; then the least-squares rigid fit
(:func:`eyetohand.solve.rigid_fit`) and the refusals:

* a scale the rigid fit cannot absorb but a similarity can: "the touches are 1.020× farther apart
  than the plate says: square size 20.4 mm, or robot units?";
* one touch the others do not explain (4+ touches): off the plate's plane ("… mm off the plane of
  the other touches"; with exactly 4 any one of them may be it: "the touches are not on one plane"),
  on another corner ("… at corner r2c6: wrong corner?"), or just off;
* no single touch to blame: "the touches do not fit the plate rigidly …: did the plate move between
  the image and the touches?".

``tolerance_mm`` (default 1.0 mm) is the largest residual a touch may keep: a pointer read with 0.2 mm
noise per axis leaves residuals of ~0.35 mm (0.8 mm at the worst of 4 touches, 1 in 1000), a wrong
corner is a pitch away, a 2 % scale error 1.4 mm at a corner 70 mm from the touches' centre.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from eyetohand.core import InputError, read_bounded_text, read_csv
from eyetohand.solve import RigidFit, rigid_fit
from eyetohand.vision import PlateSpec

SNAP_FRACTION = 0.3
SNAP_MAX_PX = 10.0
"""A touch's pixel must lie within this fraction of the corner spacing of a detected corner, and
within ``SNAP_MAX_PX``: a pixel read off the annotated image is good to a few pixels."""
TOLERANCE_MM = 1.0
COLLINEAR_RATIO = 0.05
"""The touched corners' smaller spread / larger spread below this: on one line."""
NOISE_FLOOR_MM = 0.01
"""The touch noise used is never below this (3 touches that agree to 1 µm are luck, not a 1 µm robot)."""


@dataclass(frozen=True)
class Touch:
    """One touch: the pixel read, the robot's reading, its image (0-based), its name, its line."""

    uv_px: tuple[float, float]
    xyz_mm: tuple[float, float, float]
    image: int
    id: str
    line: int

    @property
    def where(self) -> str:
        return f"touch {self.id} (line {self.line})"

    def to_dict(self) -> dict:
        return {
            "image": self.image,
            "u": self.uv_px[0],
            "v": self.uv_px[1],
            "x": self.xyz_mm[0],
            "y": self.xyz_mm[1],
            "z": self.xyz_mm[2],
            "id": self.id,
            "line": self.line,
        }

    @classmethod
    def from_dict(cls, d: dict) -> Touch:
        return cls(
            (float(d["u"]), float(d["v"])),
            (float(d["x"]), float(d["y"]), float(d["z"])),
            int(d["image"]),
            str(d["id"]),
            int(d["line"]),
        )


def load_touches(path: str | os.PathLike, images: list[str]) -> list[Touch]:
    """The touches of a file (module docstring); ``images``: the plate images' names, in order."""
    return touches_from_text(read_bounded_text(Path(path), what="a touches file"), str(path), images)


def touches_from_text(text: str, source: str, images: list[str]) -> list[Touch]:
    table = read_csv(text, source)
    header = [h.strip().lower() for h in table.rows[table.first]]
    need = ["u", "v", "x", "y", "z"]
    missing = [c for c in need if c not in header]
    if missing:
        raise InputError(
            f"missing column {missing[0]!r}; a touches file has columns [image,]u,v,x,y,z[,id]",
            source=source,
            line=table.first + 1,
        )
    col = {c: header.index(c) for c in header}
    if "image" not in col and len(images) > 1:
        raise InputError(
            f"{len(images)} plate images: the touches need an 'image' column (file name or number)",
            source=source,
            line=table.first + 1,
        )
    names = {Path(n).name: k for k, n in enumerate(images)}
    out: list[Touch] = []
    for k, row in enumerate(table.rows[table.first + 1 :], start=table.first + 2):
        if not any(c.strip() for c in row):
            continue
        vals = []
        for c in need:
            raw = row[col[c]].strip() if col[c] < len(row) else ""
            try:
                v = float(raw)
            except ValueError:
                v = math.nan
            if not math.isfinite(v):
                raise InputError(f"{raw!r} is not a finite number", source=source, line=k, field=c)
            vals.append(v)
        img = 0
        if "image" in col:
            raw = row[col["image"]].strip() if col["image"] < len(row) else ""
            if raw in names:
                img = names[raw]
            elif raw.isdigit() and 1 <= int(raw) <= len(images):
                img = int(raw) - 1
            else:
                raise InputError(
                    f"{raw!r} is none of the plate images ({', '.join(Path(n).name for n in images)}) "
                    f"nor a number 1..{len(images)}",
                    source=source,
                    line=k,
                    field="image",
                )
        tid = (
            row[col["id"]].strip() if "id" in col and col["id"] < len(row) and row[col["id"]].strip() else ""
        )
        out.append(Touch((vals[0], vals[1]), (vals[2], vals[3], vals[4]), img, tid or str(len(out) + 1), k))
    if not out:
        raise InputError("no touches: a plate's placement needs at least 3", source=source)
    return out


@dataclass(frozen=True)
class Placement:
    """One image's plate placed in the robot frame: the rigid fit, the corners touched, the noise."""

    image: int
    fit: RigidFit
    corners: tuple[int, ...]  # the plate point each touch snapped to
    noise_mm: float  # the touch noise σ per axis used for the covariance

    @property
    def covariance(self) -> np.ndarray:
        return self.fit.covariance(self.noise_mm)


def snap_radius_px(spacing_px: float) -> float:
    """How far (px) a touch's pixel may be from its corner, for corners ``spacing_px`` apart."""
    return min(SNAP_FRACTION * spacing_px, SNAP_MAX_PX)


def snap(touches: list[Touch], uv_px: np.ndarray, spacing_px: float, spec: PlateSpec) -> list[int]:
    """The detected corner (index) each touch's pixel is on; refused naming the touch when none is
    within ``SNAP_FRACTION`` of the spacing, or two touches share one."""
    ids = spec.ids()
    radius = snap_radius_px(spacing_px)
    out: list[int] = []
    for t in touches:
        d = np.nan_to_num(np.linalg.norm(uv_px - np.array(t.uv_px), axis=1), nan=np.inf)  # NaN: not seen
        i = int(np.argmin(d))
        if d[i] > radius:
            raise InputError(
                f"{t.where}: (u, v) = ({t.uv_px[0]:g}, {t.uv_px[1]:g}) px is {d[i]:.1f} px from the nearest "
                f"detected {spec.what[:-1]} {ids[i]} (snap radius {radius:.1f} px): read the pixel off the "
                "annotated image (--annotate)"
            )
        if i in out:
            other = touches[out.index(i)]
            raise InputError(
                f"{t.where} and {other.where} are on the same {spec.what[:-1]} {ids[i]}: coincident touches; "
                "touch distinct corners (A-D on the annotated image)"
            )
        out.append(i)
    return out


def place(
    touches: list[Touch],
    corners: list[int],
    spec: PlateSpec,
    image: int,
    *,
    tolerance_mm: float = TOLERANCE_MM,
    touch_noise_mm: float | None = None,
) -> Placement:
    """The plate's placement from one image's touches (module docstring), or the refusal."""
    ids = spec.ids()
    names = ", ".join(t.id for t in touches)
    if len(touches) < 3:
        raise InputError(
            f"image {image + 1}: {len(touches)} touch(es) ({names}); a plate's placement needs at least 3 "
            "touches of corners not on one line"
        )
    P = spec.points_mm()[corners]
    X = np.array([t.xyz_mm for t in touches])
    s = np.linalg.svd(P[:, :2] - P[:, :2].mean(axis=0), compute_uv=False)
    if s[1] < COLLINEAR_RATIO * s[0]:
        raise InputError(
            f"image {image + 1}: the touched {spec.what} {', '.join(ids[i] for i in corners)} lie on one "
            "line: the plate could turn about it; touch at least 3 corners not on one line (A, B, C)"
        )
    fit = rigid_fit(P, X)
    extent = float(np.max(np.linalg.norm(P - P.mean(axis=0), axis=1)))
    worst = float(np.max(np.linalg.norm(fit.residuals_mm, axis=1)))
    if (
        worst > tolerance_mm
        and abs(fit.scale - 1) * extent > tolerance_mm
        and fit.scaled_rms_mm < 0.5 * fit.rms_mm
    ):
        size = "square size" if spec.kind == "chessboard" else "dot pitch"
        raise InputError(
            f"image {image + 1}: the touches are {fit.scale:.3f}x farther apart than the plate says: "
            f"{size} {spec.pitch_mm * fit.scale:.4g} mm (not {spec.pitch_mm:g}), or robot units?"
        )
    if worst > tolerance_mm or _off_plane(fit) > tolerance_mm / 2:
        _blame(touches, P, X, fit, spec, corners, image, tolerance_mm)
    n = len(touches)
    rss = float((fit.residuals_mm**2).sum())
    noise = math.sqrt(rss / (3 * n - 6)) if touch_noise_mm is None else float(touch_noise_mm)
    return Placement(image, fit, tuple(corners), max(noise, NOISE_FLOOR_MM))


def _blame(touches, P, X, fit: RigidFit, spec: PlateSpec, corners, image: int, tol: float) -> None:
    """Refuse a placement the touches do not fit: one touch to blame when the others fit (4+)."""
    ids = spec.ids()
    n = len(touches)
    found = []  # (k, off, fit of the others) for each touch whose removal leaves a fitting set
    for k in range(n if n >= 4 else 0):
        keep = [j for j in range(n) if j != k]
        sv = np.linalg.svd(P[keep, :2] - P[keep, :2].mean(axis=0), compute_uv=False)
        if sv[1] < COLLINEAR_RATIO * sv[0]:
            continue
        f = rigid_fit(P[keep], X[keep])
        if np.max(np.linalg.norm(f.residuals_mm, axis=1)) <= tol and _off_plane(f) <= tol / 2:
            found.append((k, X[k] - f.apply(P[k : k + 1])[0], f))
    if found:
        k, off, f = max(found, key=lambda c: float(np.linalg.norm(c[1])))
        t = touches[k]
        normal = float(off @ f.R[:, 2])
        if abs(normal) > 0.8 * np.linalg.norm(off):
            if len(found) > 1:
                raise InputError(
                    f"image {image + 1}: the touches are not on one plane: one is {abs(normal):.2f} mm off "
                    f"the plane of the other {n - 1} ({n} touches cannot tell which; "
                    f"{'a 5th' if n == 4 else 'another touch, away from these,'} would): touched "
                    "above or below the plate (its edge, a block, the pointer not down)?"
                )
            raise InputError(
                f"{t.where} is {abs(normal):.2f} mm off the plane of the other touches (the plate's "
                "plane): touched above or below the plate (its edge, a block, the pointer not down)?"
            )
        in_plane = f.R.T @ (X[k] - f.t_mm)  # where the robot touched, plate frame
        pts = spec.points_mm()
        j = int(np.argmin(np.linalg.norm(pts[:, :2] - in_plane[:2], axis=1)))
        near = float(np.linalg.norm(pts[j, :2] - in_plane[:2]))
        if j != corners[k] and near < 0.25 * spec.pitch_mm:
            raise InputError(
                f"{t.where} was read at {spec.what[:-1]} {ids[corners[k]]}, but the robot touched "
                f"{np.linalg.norm(off):.2f} mm from it, at {spec.what[:-1]} {ids[j]}: wrong corner?"
            )
        raise InputError(
            f"{t.where} is {np.linalg.norm(off):.2f} mm from where the other touches place its "
            f"{spec.what[:-1]} {ids[corners[k]]} (tolerance {tol:g} mm): touch it again"
        )
    res = np.linalg.norm(fit.residuals_mm, axis=1)
    k = int(np.argmax(res))
    raise InputError(
        f"image {image + 1}: the touches do not fit the plate rigidly: RMS {fit.rms_mm:.2f} mm, "
        f"{res[k]:.2f} mm at {touches[k].where} (tolerance {tol:g} mm): did the plate move between "
        "the image and the touches, or is a touch on the wrong corner?"
    )


def _off_plane(fit: RigidFit) -> float:
    """The largest residual (mm) along the plate's normal."""
    return float(np.max(np.abs(fit.residuals_mm @ fit.R[:, 2])))


__all__ = [
    "NOISE_FLOOR_MM",
    "Placement",
    "SNAP_FRACTION",
    "TOLERANCE_MM",
    "Touch",
    "load_touches",
    "place",
    "snap",
    "snap_radius_px",
    "touches_from_text",
]
