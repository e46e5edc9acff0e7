"""The calibrated conveyor (:class:`ConveyorCalibration`): the camera map for parts on the belt, the
belt, the encoder and the robot's window; mapping a sighting to the robot, and the calibration's file
(``save``/``load``, schema :data:`SCHEMA` version :data:`SCHEMA_VERSION`)."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from eyetohand.calibration import Calibration
from eyetohand.cell.conveyor.records import Belt, Encoder
from eyetohand.core import InputError, atomic_write_text, read_bounded_text

SCHEMA = "eyetohand.conveyor"
SCHEMA_VERSION = 1


@dataclass(frozen=True)
class ConveyorCalibration:
    """Camera map for parts on the belt + belt + encoder + the robot's window.

    ``surface``: (c0, c1, c2, x0, y0), the parts' top plane ``z = c0 + c1 (x − x0) + c2 (y − y0)``.
    ``window_mm``: (lo, hi), the robot's reach along the belt: a part is pickable when
    ``direction · p`` lies in it. ``latch_counts``: counts by which an image's latched count runs
    ahead of its exposure (applied to every image mapped). ``report``: the calibration report as its
    JSON record (:meth:`~eyetohand.cell.conveyor.report.ConveyorReport.to_dict`).
    """

    calibration: Calibration
    surface: tuple[float, float, float, float, float]
    belt: Belt
    encoder: Encoder
    window_mm: tuple[float, float]
    latch_counts: float = 0.0
    sigma_latch_counts: float | None = None
    report: dict | None = None
    notes: tuple[str, ...] = field(default=())

    # ---------------------------------------------------------------- mapping
    def image_to_robot_at_image(self, uv_px, *, allow_outside: bool = False) -> np.ndarray:
        """(N, 2) px → (N, 3) mm: where the part was at its exposure (the camera map and surface);
        a pixel outside the image region the sightings covered is refused unless ``allow_outside``."""
        uv = np.atleast_2d(np.asarray(uv_px, float))
        xy = self.calibration.image_to_robot(uv, allow_outside=allow_outside)[:, :2]
        c0, c1, c2, x0, y0 = self.surface
        z = c0 + c1 * (xy[:, 0] - x0) + c2 * (xy[:, 1] - y0)
        return np.column_stack([xy, z])

    def tracking_form(self, uv_px, e_image) -> dict:
        """What a controller's own tracking wants: the part's position at the latched count
        ``e_image`` (latch delay applied) and the belt vector; the controller adds
        ``belt_mm_per_count · delta(e_image, e_now)`` itself."""
        e_img = self.encoder.check(e_image, "e_image")
        b = self.belt.vector_mm_per_count
        p = self.image_to_robot_at_image(uv_px) + b * self.latch_counts
        return {"position_mm": p, "e_image": e_img, "belt_mm_per_count": b}

    def image_to_robot_at(self, uv_px, e_image, e_now, *, allow_outside: bool = False) -> np.ndarray:
        """(N, 2) px seen at latched counts ``e_image`` → (N, 3) mm when the encoder reads ``e_now``
        (scalars or (N,)). A part outside the robot's window is refused with the distance (mm), and
        one seen outside the calibrated image region likewise, unless ``allow_outside``."""
        uv = np.atleast_2d(np.asarray(uv_px, float))
        n = len(uv)
        de = np.broadcast_to(self.encoder.delta(e_image, e_now), (n,)).astype(float)
        b = self.belt.vector_mm_per_count
        p = (
            self.image_to_robot_at_image(uv, allow_outside=allow_outside)
            + b * (de + self.latch_counts)[:, None]
        )
        if not allow_outside:
            self.check_window(p)
        return p

    def rz_deg(self, uv_px, angle_deg, *, symmetry: int = 1, tool_rz_offset_deg: float | None = None):
        """(N,) robot rz (deg) of parts seen at ``uv_px`` with image angles ``angle_deg`` (deg, +u
        towards +v): the belt translates a part, it does not turn it, so this is the camera map's rz
        (:meth:`Calibration.map`, folded by ``symmetry``, offset by ``tool_rz_offset_deg``)."""
        m = self.calibration.map(
            uv_px,
            None,
            angle_deg=angle_deg,
            allow_outside=True,  # the position's guard (image region, window) is the caller's
            symmetry=symmetry,
            tool_rz_offset_deg=tool_rz_offset_deg,
            with_sigma=False,
        )
        assert m.rz_deg is not None  # map answers rz whenever an angle is given
        return m.rz_deg

    def check_window(self, xyz_mm) -> None:
        s = np.asarray(xyz_mm, float) @ np.array(self.belt.direction)
        lo, hi = self.window_mm
        for i, si in enumerate(np.atleast_1d(s)):
            label = f"point {i}: " if np.size(s) > 1 else ""
            if si > hi:
                raise InputError(
                    f"{label}the part is {si - hi:.1f} mm downstream of the robot window's far "
                    f"end ({lo:.1f}..{hi:.1f} mm along the belt): it has left the window"
                )
            if si < lo:
                raise InputError(
                    f"{label}the part is {lo - si:.1f} mm upstream of the robot window "
                    f"({lo:.1f}..{hi:.1f} mm along the belt): it has not reached it yet"
                )

    # ---------------------------------------------------------------- persistence
    def to_dict(self) -> dict:
        return {
            "schema": SCHEMA,
            "schema_version": SCHEMA_VERSION,
            "calibration": self.calibration.to_dict(),
            "surface": list(self.surface),
            "belt": self.belt.to_dict(),
            "encoder": self.encoder.to_dict(),
            "window_mm": list(self.window_mm),
            "latch_counts": self.latch_counts,
            "sigma_latch_counts": self.sigma_latch_counts,
            "report": self.report,
            "notes": list(self.notes),
        }

    def save(self, path: str | os.PathLike) -> Path:
        return atomic_write_text(path, json.dumps(self.to_dict(), indent=2, allow_nan=False) + "\n")

    @classmethod
    def from_dict(cls, d: dict, source: str = "<dict>") -> ConveyorCalibration:
        if not isinstance(d, dict) or d.get("schema") != SCHEMA:
            raise InputError(f"{source}: not an eyetohand conveyor calibration (no schema {SCHEMA!r})")
        if d.get("schema_version") != SCHEMA_VERSION:
            raise InputError(
                f"{source}: conveyor schema_version {d.get('schema_version')!r}, "
                f"this eyetohand reads {SCHEMA_VERSION}"
            )
        try:
            return cls(
                Calibration.from_dict(d["calibration"], source),
                tuple(d["surface"]),
                Belt.from_dict(d["belt"]),
                Encoder(**d["encoder"]),
                tuple(d["window_mm"]),
                float(d.get("latch_counts", 0.0)),
                d.get("sigma_latch_counts"),
                d.get("report"),
                tuple(d.get("notes", ())),
            )
        except InputError as exc:
            raise InputError(f"{source}: {exc}") from None
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(
                f"{source}: malformed conveyor calibration ({type(exc).__name__}: {exc})"
            ) from None

    @classmethod
    def load(cls, path: str | os.PathLike) -> ConveyorCalibration:
        path = Path(path)
        try:
            d = json.loads(read_bounded_text(path, what="a conveyor calibration file"))
        except json.JSONDecodeError as exc:
            raise InputError(f"{path} line {exc.lineno}: invalid JSON ({exc.msg})") from None
        return cls.from_dict(d, str(path))


__all__ = ["ConveyorCalibration", "SCHEMA", "SCHEMA_VERSION"]
